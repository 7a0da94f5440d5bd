//! # cloi-io
//!
//! The file formats of CLOi-Mapper on Linux, one thin module per format over maintained
//! crates, shared by the simulator (`cloi-sim`), the evaluation (`cloi-eval`) and the `cloi`
//! command (`cloi-host`).
//!
//! * [`ros2`]: ROS 2 message structs (serde + CDR) and their `ros2msg` schemas.
//! * [`bag`]: writing ROS 2 bags as MCAP files.
//! * [`bag_read`]: reading ROS 2 bags (MCAP) as a time-ordered stream of sensor messages.
//! * [`camera_frame`]: camera pictures of ROS 2 messages as the mapper reads them.
//! * [`carmen`]: CARMEN logs (`.clf`, `.log`, `.gz`, `.bz2`).
//! * [`convert`]: CARMEN records to ROS 2 messages (`cloi convert`).
//! * [`tum`]: TUM and KITTI trajectories.
//! * [`map_file`]: saved maps (`.cloimap`, the core's format) to and from files.
//! * [`map_out`]: `map.pgm` + `map.yaml`, `map.png` with the trajectory, `result.mcap`.
//! * [`cloilog`]: CARMEN logs to the firmware's compact binary sensor log.
//! * [`graph_io`]: pose-graph files (g2o, TORO) and ground truth for them.
//! * [`cli`]: `cloi convert`.
//! * [`atomic`]: atomic file output (temporary file, then rename), used by every writer.
//! * [`dataset`]: where the shared evaluation datasets live, for tests and benchmarks.

pub mod atomic;
pub mod bag;
pub mod bag_read;
pub mod camera_frame;
pub mod carmen;
pub mod cli;
pub mod cloilog;
pub mod convert;
pub mod dataset;
pub mod graph_io;
pub mod map_file;
pub mod map_out;
pub mod ros2;
pub mod tum;

pub use bag::BagWriter;

use cloi_core::Se2;

/// Parses a decimal time in seconds (`976052890.244111`, `-1.5`, `12`) into nanoseconds
/// exactly, without going through `f64`. Digits past the ninth decimal are truncated.
///
/// Returns `None` for anything that is not a plain decimal number or overflows.
pub fn parse_stamp_ns(text: &str) -> Option<i64> {
    let (negative, digits) = match text.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, text.strip_prefix('+').unwrap_or(text)),
    };
    let (whole, frac) = digits.split_once('.').unwrap_or((digits, ""));
    if whole.is_empty() && frac.is_empty() {
        return None;
    }
    if !whole
        .bytes()
        .chain(frac.bytes())
        .all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let secs: i64 = if whole.is_empty() {
        0
    } else {
        whole.parse().ok()?
    };
    let mut nanos: i64 = 0;
    for (i, b) in frac.bytes().take(9).enumerate() {
        nanos += i64::from(b - b'0') * 10_i64.pow(8 - i as u32);
    }
    let total = secs.checked_mul(1_000_000_000)?.checked_add(nanos)?;
    Some(if negative { -total } else { total })
}

/// Parses a pose given as `X,Y,THETA` (metres, metres, radians), as on the command line.
///
/// # Errors
/// Not three finite numbers separated by commas.
pub fn parse_pose(text: &str) -> Result<Se2, String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{text:?}: {e}; expected X,Y,THETA"))?;
    match v[..] {
        [x, y, theta] if v.iter().all(|n| n.is_finite()) => Ok(Se2::new(x, y, theta)),
        _ => Err(format!("{text:?}: expected three finite numbers X,Y,THETA")),
    }
}

#[cfg(test)]
mod tests {
    use super::{parse_pose, parse_stamp_ns};

    #[test]
    fn stamps_parse_exactly() {
        assert_eq!(
            parse_stamp_ns("976052890.244111"),
            Some(976_052_890_244_111_000)
        );
        assert_eq!(parse_stamp_ns("12"), Some(12_000_000_000));
        assert_eq!(parse_stamp_ns("-1.5"), Some(-1_500_000_000));
        assert_eq!(parse_stamp_ns(".25"), Some(250_000_000));
        assert_eq!(parse_stamp_ns("1.1234567891"), Some(1_123_456_789));
        for bad in [
            "",
            ".",
            "1e9",
            "abc",
            "1.2.3",
            "nan",
            "99999999999999999999",
        ] {
            assert_eq!(parse_stamp_ns(bad), None, "{bad}");
        }
    }

    #[test]
    fn poses_parse_as_three_finite_numbers() {
        let p = parse_pose(" -0.04, 0 ,1.5").unwrap();
        assert_eq!((p.x, p.y, p.theta), (-0.04, 0.0, 1.5));
        for bad in ["", "1,2", "1,2,3,4", "1,nan,0", "1,inf,0", "a,b,c"] {
            assert!(parse_pose(bad).is_err(), "{bad}");
        }
    }
}
