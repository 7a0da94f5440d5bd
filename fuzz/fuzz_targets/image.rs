//! Camera images as `cloi map` takes them from a bag (`io/camera_frame.rs`), then through the
//! core's camera stage (`frontend::visual::CameraTrack`). The first byte chooses the message:
//! even, the rest is a `CompressedImage` (JPEG, PNG or anything) decoded under the mapper's
//! limits; odd, the next six bytes give a raw `Image`'s width, height, encoding and row padding
//! and the rest its pixels. Whatever decodes is tracked twice (the second time as the next
//! frame) with scratch for frames up to 160 x 120, so larger ones exercise the refusal.
#![no_main]
use libfuzzer_sys::fuzz_target;

use cloi_core::frontend::visual::frame::{scratch_bytes, MAX_FEATURES};
use cloi_core::frontend::visual::matching::Match;
use cloi_core::frontend::visual::{CameraTrack, Keypoint, TrackConfig, TrackScratch};
use cloi_core::sensor::{ImageView, Timestamp};
use cloi_host::io::camera_frame::{from_compressed, from_raw, Pixels};
use cloi_host::io::ros2::{CompressedImage, Header, Image};

const ENCODINGS: [&str; 6] = ["mono8", "rgb8", "bgr8", "8UC1", "mono16", "yuv422"];

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let pixels = if mode % 2 == 0 {
        from_compressed(&CompressedImage {
            header: Header::default(),
            format: "fuzz".into(),
            data: rest.to_vec(),
        })
    } else {
        let Some((head, body)) = rest.split_at_checked(6) else {
            return;
        };
        let width = u32::from(u16::from_le_bytes([head[0], head[1]]) % 512);
        let height = u32::from(u16::from_le_bytes([head[2], head[3]]) % 512);
        let encoding = ENCODINGS[usize::from(head[4]) % ENCODINGS.len()];
        let bytes_per_pixel = if encoding.starts_with("mono") || encoding == "8UC1" { 1 } else { 3 };
        from_raw(Image {
            header: Header::default(),
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step: width * bytes_per_pixel + u32::from(head[5] % 8),
            data: body.to_vec(),
        })
    };
    if let Ok(p) = pixels {
        track(&p);
    }
});

fn track(p: &Pixels) {
    let mut bytes = vec![0u8; scratch_bytes(160, 120)];
    let mut corners = vec![Keypoint::default(); MAX_FEATURES];
    let mut matches = vec![Match::default(); MAX_FEATURES];
    let mut cam = Box::new(CameraTrack::new());
    for stamp in [1, 2] {
        let Ok(view) = ImageView::new_checked(
            Timestamp::from_nanos(stamp),
            p.width,
            p.height,
            p.stride,
            p.format,
            &p.data,
        ) else {
            return;
        };
        let mut scratch = TrackScratch {
            bytes: &mut bytes,
            corners: &mut corners,
            matches: &mut matches,
        };
        if let Ok(step) = cam.track(stamp, &view, &TrackConfig::default(), &mut scratch) {
            assert!(step.tracked <= step.features);
        }
    }
}
