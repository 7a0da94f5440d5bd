//! The training and evaluation images: which files (a folder or a pattern), read to grey, and
//! their rotated BRIEF descriptors from the core's frame pipeline.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use cloi_core::frontend::visual::frame::{scratch_bytes, FrameFeatures, MAX_FEATURES};
use cloi_core::frontend::visual::{Descriptor, FastConfig, Keypoint};
use cloi_core::sensor::{ImageView, PixelFormat, Timestamp};

use crate::io::camera_frame::{self, Pixels};
use crate::io::ros2::CompressedImage;

/// The file names an image listing keeps.
const EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

/// Whether `name` matches `pattern`, where `*` stands for any run of characters and `?` for
/// one.
fn wildcard(pattern: &[char], name: &[char]) -> bool {
    // Iterative matching with one backtrack point (the last `*`).
    let (mut p, mut n) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while n < name.len() {
        match pattern.get(p) {
            Some('*') => {
                star = Some((p, n));
                p += 1;
            }
            Some(&c) if c == '?' || Some(&c) == name.get(n) => {
                p += 1;
                n += 1;
            }
            _ => match star {
                Some((sp, sn)) => {
                    p = sp + 1;
                    n = sn + 1;
                    star = Some((sp, sn + 1));
                }
                None => return false,
            },
        }
    }
    pattern
        .get(p..)
        .is_some_and(|rest| rest.iter().all(|&c| c == '*'))
}

/// The order of image files: by the number their name starts with (`2.jpg` before
/// `10.jpg`), then by name.
fn image_order(path: &Path) -> (u64, String) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let digits: String = name.chars().take_while(char::is_ascii_digit).collect();
    (digits.parse().unwrap_or(u64::MAX), name)
}

/// The images of `spec`: every JPEG and PNG file of a folder, or the files matching a pattern
/// whose last component holds `*` or `?` (`dir/*.jpg`), in numeric-then-name order.
///
/// # Errors
/// The folder cannot be read, or nothing matches.
pub fn list_images(spec: &str) -> Result<Vec<PathBuf>> {
    let path = Path::new(spec);
    let (dir, pattern): (PathBuf, Option<Vec<char>>) = if path.is_dir() {
        (path.to_path_buf(), None)
    } else {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if !name.contains(['*', '?']) {
            if path.is_file() {
                return Ok(vec![path.to_path_buf()]);
            }
            bail!("{spec}: no such folder or file");
        }
        let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
        (
            parent.map_or_else(|| PathBuf::from("."), Path::to_path_buf),
            Some(name.chars().collect()),
        )
    };
    let mut found = Vec::new();
    for entry in std::fs::read_dir(&dir).with_context(|| format!("reading {}", dir.display()))? {
        let p = entry?.path();
        if !p.is_file() {
            continue;
        }
        let name: Vec<char> = p
            .file_name()
            .map(|n| n.to_string_lossy().chars().collect())
            .unwrap_or_default();
        let keep = match &pattern {
            Some(pat) => wildcard(pat, &name),
            None => p.extension().is_some_and(|e| {
                EXTENSIONS
                    .iter()
                    .any(|x| e.to_string_lossy().eq_ignore_ascii_case(x))
            }),
        };
        if keep {
            found.push(p);
        }
    }
    if found.is_empty() {
        bail!("{spec}: no JPEG or PNG image found");
    }
    found.sort_by_key(|p| image_order(p));
    Ok(found)
}

/// An image file decoded to grey (JPEG or PNG, as the camera stage decodes them).
///
/// # Errors
/// The file cannot be read or decoded.
pub fn read_grey(path: &Path) -> Result<Pixels> {
    let data = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let format = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let msg = CompressedImage {
        format,
        data,
        ..CompressedImage::default()
    };
    camera_frame::from_compressed(&msg).with_context(|| format!("decoding {}", path.display()))
}

/// The descriptors of a grey image, from the core's frame pipeline with the default corner
/// settings (at most [`MAX_FEATURES`]).
///
/// # Errors
/// Sizes the core refuses.
pub fn descriptors_of(pixels: &Pixels) -> Result<Vec<Descriptor>> {
    if pixels.format != PixelFormat::Mono8 {
        bail!("a grey image was expected");
    }
    let view = ImageView::new_checked(
        Timestamp::from_nanos(0),
        pixels.width,
        pixels.height,
        pixels.stride,
        PixelFormat::Mono8,
        &pixels.data,
    )
    .map_err(|e| anyhow::anyhow!("image refused: {e:?}"))?;
    let mut scratch = vec![0u8; scratch_bytes(pixels.width, pixels.height)];
    let mut corners = vec![Keypoint::default(); MAX_FEATURES];
    let mut features = Box::new(FrameFeatures::new());
    features
        .extract(&view, &FastConfig::default(), &mut scratch, &mut corners)
        .map_err(|e| anyhow::anyhow!("features not extracted: {e:?}"))?;
    Ok(features.descriptors().to_vec())
}

/// The descriptors of every image of `paths`, one list per image.
///
/// # Errors
/// An image that cannot be read or described.
pub fn describe_images(paths: &[PathBuf]) -> Result<Vec<Vec<Descriptor>>> {
    paths
        .iter()
        .map(|p| descriptors_of(&read_grey(p)?).with_context(|| p.display().to_string()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn matches(p: &str, n: &str) -> bool {
        wildcard(
            &p.chars().collect::<Vec<_>>(),
            &n.chars().collect::<Vec<_>>(),
        )
    }

    #[test]
    fn wildcards_match_like_a_shell() {
        assert!(matches("*.jpg", "12.jpg"));
        assert!(matches("?.jpg", "1.jpg"));
        assert!(!matches("?.jpg", "12.jpg"));
        assert!(matches("a*b*c", "aXXbYc"));
        assert!(!matches("*.jpg", "a.png"));
        assert!(matches("*", ""));
    }

    #[test]
    fn images_sort_by_their_number() {
        let mut v: Vec<PathBuf> = ["10.jpg", "2.jpg", "b.jpg", "1.jpg"]
            .iter()
            .map(PathBuf::from)
            .collect();
        v.sort_by_key(|p| image_order(p));
        let names: Vec<_> = v.iter().map(|p| p.to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["1.jpg", "2.jpg", "10.jpg", "b.jpg"]);
    }
}
