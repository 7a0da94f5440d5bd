//! From decoded ROS 2 messages to the core's sensor frames ([`cloi_core::sensor`]), which
//! borrow the message buffers for one call.

use anyhow::{bail, Context, Result};
use cloi_core::sensor::{
    ImageView, ImuSample, LaserScanView, OdometrySample, PixelFormat, ScanError, ScanGeometry,
    Timestamp, Twist2,
};
use cloi_core::Se2;

use super::ros2::{covariance_unknown, CompressedImage, Image, Imu, LaserScan, Odometry};

/// The header time of a message as a core time stamp.
pub fn stamp(t: super::ros2::Time) -> Timestamp {
    Timestamp::from_nanos(t.to_nanos())
}

/// A checked view of a scan message (intensities are used when there is one per range).
///
/// # Errors
/// [`ScanError`] when the scan as a whole is unusable.
pub fn scan_view(scan: &LaserScan) -> Result<LaserScanView<'_>, ScanError> {
    let geometry = ScanGeometry {
        angle_min: scan.angle_min,
        angle_increment: scan.angle_increment,
        range_min: scan.range_min,
        range_max: scan.range_max,
    };
    let intensities = (!scan.intensities.is_empty()).then_some(scan.intensities.as_slice());
    LaserScanView::new_checked(
        stamp(scan.header.stamp),
        geometry,
        &scan.ranges,
        intensities,
    )
}

/// The planar odometry sample of a message (yaw from the quaternion; the x, y, yaw block of
/// the covariance when it is given, i.e. not all zero and not marked unknown).
pub fn odometry_sample(odom: &Odometry) -> OdometrySample {
    let (x, y, theta) = odom.pose.pose.to_planar();
    let c = &odom.pose.covariance;
    let given = !covariance_unknown(c) && c.iter().any(|&v| v != 0.0);
    // Rows/columns 0, 1 and 5 (x, y, rotation about z) of the 6x6 matrix.
    let idx = [0usize, 1, 5];
    let covariance = given.then(|| idx.map(|r| idx.map(|k| c[r * 6 + k])));
    OdometrySample {
        stamp: stamp(odom.header.stamp),
        pose: Se2::new(x, y, theta),
        twist: Twist2 {
            vx: odom.twist.twist.linear.x,
            vy: odom.twist.twist.linear.y,
            wz: odom.twist.twist.angular.z,
        },
        covariance,
    }
}

/// The inertial sample of a message (acceleration only when its covariance is not marked
/// unknown).
pub fn imu_sample(imu: &Imu) -> ImuSample {
    let w = imu.angular_velocity;
    let a = imu.linear_acceleration;
    ImuSample {
        stamp: stamp(imu.header.stamp),
        angular_rate: [w.x, w.y, w.z],
        linear_acceleration: (!covariance_unknown(&imu.linear_acceleration_covariance))
            .then_some([a.x, a.y, a.z]),
    }
}

/// The pixel format of a ROS image encoding the core reads.
pub fn pixel_format(encoding: &str) -> Option<PixelFormat> {
    match encoding {
        "mono8" | "8UC1" => Some(PixelFormat::Mono8),
        "rgb8" => Some(PixelFormat::Rgb8),
        "bgr8" | "8UC3" => Some(PixelFormat::Bgr8),
        _ => None,
    }
}

/// A checked view of a raw image message.
///
/// # Errors
/// An encoding other than mono8/rgb8/bgr8, or sizes that do not fit the data.
pub fn image_view(image: &Image) -> Result<ImageView<'_>> {
    let Some(format) = pixel_format(&image.encoding) else {
        bail!("unsupported image encoding {:?}", image.encoding);
    };
    Ok(ImageView::new_checked(
        stamp(image.header.stamp),
        image.width as usize,
        image.height as usize,
        image.step as usize,
        format,
        &image.data,
    )?)
}

/// A decoded compressed image: raw pixels the core can view.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecodedImage {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Layout of `data` (mono8 for grey pictures, else rgb8).
    pub format: PixelFormat,
    /// Pixels, rows packed.
    pub data: Vec<u8>,
}

impl DecodedImage {
    /// A view for the core.
    ///
    /// # Errors
    /// Never for a decoded picture; kept fallible like every view.
    pub fn view(&self, stamp: Timestamp) -> Result<ImageView<'_>> {
        let stride = self.width * self.format.bytes_per_pixel();
        Ok(ImageView::new_checked(
            stamp,
            self.width,
            self.height,
            stride,
            self.format,
            &self.data,
        )?)
    }
}

/// Decodes a `CompressedImage` (jpeg or png, found from the data itself).
///
/// # Errors
/// Data that is neither a readable JPEG nor PNG.
pub fn decode_compressed(msg: &CompressedImage) -> Result<DecodedImage> {
    let img = image::load_from_memory(&msg.data)
        .with_context(|| format!("decoding a compressed image ({:?})", msg.format))?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    Ok(if img.color().has_color() {
        DecodedImage {
            width,
            height,
            format: PixelFormat::Rgb8,
            data: img.into_rgb8().into_raw(),
        }
    } else {
        DecodedImage {
            width,
            height,
            format: PixelFormat::Mono8,
            data: img.into_luma8().into_raw(),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::ros2::{Header, Pose, Time};

    #[test]
    fn scan_message_to_view() {
        let scan = LaserScan {
            header: Header::new(Time::from_nanos(42), "laser"),
            angle_min: -1.0,
            angle_increment: 0.1,
            range_min: 0.1,
            range_max: 10.0,
            ranges: vec![1.0, f32::NAN, 81.83, 2.0],
            ..Default::default()
        };
        let view = scan_view(&scan).unwrap();
        assert_eq!(view.stamp(), Timestamp(42));
        assert_eq!(view.stats().valid, 2);
        assert_eq!(view.stats().above_max, 1);
        let empty = LaserScan::default();
        assert_eq!(scan_view(&empty), Err(ScanError::NoBeams));
    }

    #[test]
    fn odometry_message_to_sample() {
        let mut odom = Odometry::default();
        odom.pose.pose = Pose::planar(1.0, 2.0, 0.5);
        odom.twist.twist.angular.z = 0.25;
        let s = odometry_sample(&odom);
        assert!((s.pose.theta - 0.5).abs() < 1e-12);
        assert_eq!(s.twist.wz, 0.25);
        assert_eq!(s.covariance, None);
        odom.pose.covariance[0] = 0.1;
        odom.pose.covariance[35] = 0.3;
        odom.pose.covariance[5] = 0.01;
        let c = odometry_sample(&odom).covariance.unwrap();
        assert_eq!(c, [[0.1, 0.0, 0.01], [0.0, 0.0, 0.0], [0.0, 0.0, 0.3]]);
    }

    #[test]
    fn images_to_views() {
        let img = Image {
            height: 2,
            width: 2,
            encoding: "bgr8".into(),
            step: 6,
            data: vec![0; 12],
            ..Default::default()
        };
        assert_eq!(image_view(&img).unwrap().format(), PixelFormat::Bgr8);
        let bad = Image {
            encoding: "16UC1".into(),
            ..img.clone()
        };
        assert!(image_view(&bad).is_err());
        let short = Image {
            data: vec![0; 5],
            ..img
        };
        assert!(image_view(&short).is_err());

        // A PNG made with the image crate decodes back to the same grey pixels.
        let grey = image::GrayImage::from_raw(3, 2, vec![0, 50, 100, 150, 200, 250]).unwrap();
        let mut png = Vec::new();
        grey.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let msg = CompressedImage {
            format: "png".into(),
            data: png,
            ..Default::default()
        };
        let decoded = decode_compressed(&msg).unwrap();
        assert_eq!(decoded.format, PixelFormat::Mono8);
        let view = decoded.view(Timestamp(1)).unwrap();
        assert_eq!(view.luminance(2, 1), Some(250));
        assert!(decode_compressed(&CompressedImage::default()).is_err());
    }
}
