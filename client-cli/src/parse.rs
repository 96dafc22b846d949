//! Parsers for command-line values.

use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use glam::DVec3;
use pointfarm_render::color::{ColorMode, ColorRamp, ColorRange};
use pointfarm_render::encode::video::VideoCodec;
use pointfarm_render::request::PointSize;

/// A number of seconds within `range`, for flags that take a duration.
pub fn seconds_within(value: &str, range: std::ops::RangeInclusive<f64>) -> Result<f64, String> {
    match value.parse::<f64>() {
        Ok(seconds) if seconds.is_finite() && range.contains(&seconds) => Ok(seconds),
        _ => Err(format!(
            "'{value}' is not a number of seconds from {} to {}",
            range.start(),
            range.end()
        )),
    }
}

/// `1280x720`.
pub fn size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}' is not a size like 1280x720"))?;
    let side = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("'{s}' is not a size like 1280x720"))
    };
    Ok((side(w)?, side(h)?))
}

/// `x,y,z` with finite numbers.
pub fn vec3(s: &str) -> Result<DVec3, String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("'{s}' is not a point like x,y,z"));
    }
    let mut v = [0.0; 3];
    for (slot, part) in v.iter_mut().zip(parts) {
        *slot = part
            .trim()
            .parse::<f64>()
            .map_err(|_| format!("'{part}' is not a number"))?;
        if !slot.is_finite() {
            return Err(format!("'{part}' is not a finite number"));
        }
    }
    Ok(DVec3::from_array(v))
}

/// `#rrggbb`, `#rrggbbaa` (the `#` optional) or `transparent`.
pub fn color(s: &str) -> Result<[u8; 4], String> {
    if s.eq_ignore_ascii_case("transparent") {
        return Ok([0, 0, 0, 0]);
    }
    let hex = s.trim_start_matches('#');
    let bad = || format!("'{s}' is not a color like #1e1e24, #1e1e2480 or transparent");
    if !(hex.len() == 6 || hex.len() == 8) || !hex.is_ascii() {
        return Err(bad());
    }
    let byte = |i: usize| u8::from_str_radix(&hex[i..i + 2], 16).map_err(|_| bad());
    let alpha = if hex.len() == 8 { byte(6)? } else { 255 };
    Ok([byte(0)?, byte(2)?, byte(4)?, alpha])
}

/// An RGBA color that prints as `#rrggbbaa` (for defaults shown in the help).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rgba(pub [u8; 4]);

impl std::fmt::Display for Rgba {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [r, g, b, a] = self.0;
        write!(f, "#{r:02x}{g:02x}{b:02x}{a:02x}")
    }
}

/// [`color`] as an [`Rgba`].
pub fn rgba(s: &str) -> Result<Rgba, String> {
    color(s).map(Rgba)
}

/// `rgb`, `intensity`, `elevation`, `classification`, `return`, or a color like `#ff8000`.
pub fn color_mode(s: &str) -> Result<ColorMode, String> {
    match s.to_ascii_lowercase().as_str() {
        "rgb" => Ok(ColorMode::Rgb),
        "intensity" => Ok(ColorMode::Intensity),
        "elevation" | "height" => Ok(ColorMode::Elevation),
        "classification" | "class" => Ok(ColorMode::Classification),
        "return" | "return-number" => Ok(ColorMode::ReturnNumber),
        _ => match color(s) {
            Ok([r, g, b, _]) => Ok(ColorMode::Fixed([r, g, b])),
            Err(_) => Err(format!(
                "'{s}' is not a color mode (rgb, intensity, elevation, classification, return, \
                 or a color like #ff8000)"
            )),
        },
    }
}

/// `MIN..MAX`, e.g. `-12.5..340` (checked with the request: finite, MIN below MAX).
pub fn color_range(s: &str) -> Result<ColorRange, String> {
    let bad = || format!("'{s}' is not a range like 0..255 or -12.5..340");
    let (min, max) = s.split_once("..").ok_or_else(bad)?;
    let number = |v: &str| v.trim().parse::<f64>().map_err(|_| bad());
    Ok(ColorRange {
        min: number(min)?,
        max: number(max)?,
    })
}

/// A ramp's name: `viridis`, `inferno`, `turbo` or `grey`.
pub fn color_ramp(s: &str) -> Result<ColorRamp, String> {
    ColorRamp::from_name(s).ok_or_else(|| {
        let names: Vec<&str> = ColorRamp::ALL.iter().map(|r| r.name()).collect();
        format!("'{s}' is not a ramp ({})", names.join(", "))
    })
}

/// A finite positive number.
/// `auto` or a side in pixels (the request's validation checks its range).
pub fn point_size(s: &str) -> Result<PointSize, String> {
    match s.trim() {
        "auto" => Ok(PointSize::Adaptive),
        side => match side.parse::<u32>() {
            Ok(0) | Err(_) => Err(format!(
                "point size {s:?} is invalid: use auto or a whole number of pixels from 1"
            )),
            Ok(side) => Ok(PointSize::Fixed(side)),
        },
    }
}

pub fn positive(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a positive number")),
    }
}

/// A number of bytes: `512MiB`, `4GiB`, `2G`, `300M`, `65536` (a suffix is binary: `G` is
/// `GiB`).
pub fn bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let digits = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(digits);
    let shift = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kib" | "kb" => 10,
        "m" | "mib" | "mb" => 20,
        "g" | "gib" | "gb" => 30,
        "t" | "tib" | "tb" => 40,
        _ => return Err(format!("'{s}' is not a size (like 512MiB or 4GiB)")),
    };
    match number.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 && v * ((1u64 << shift) as f64) < u64::MAX as f64 => {
            Ok((v * (1u64 << shift) as f64) as u64)
        }
        _ => Err(format!("'{s}' is not a size (like 512MiB or 4GiB)")),
    }
}

/// A finite number from 0.
pub fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a number from 0")),
    }
}

/// `--video-codec`'s parser: the render crate's codecs, by name, each with its description.
pub fn codec_parser() -> impl TypedValueParser<Value = VideoCodec> {
    PossibleValuesParser::new(
        VideoCodec::ALL.map(|codec| PossibleValue::new(codec.name()).help(codec.description())),
    )
    .try_map(|name| name.parse::<VideoCodec>())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_are_taken_within_their_range_and_said_otherwise() {
        assert_eq!(seconds_within("0.5", 0.1..=3600.0), Ok(0.5));
        assert_eq!(seconds_within("0", 0.0..=3600.0), Ok(0.0));
        for bad in ["0.05", "3601", "NaN", "inf", "soon"] {
            assert_eq!(
                seconds_within(bad, 0.1..=3600.0),
                Err(format!(
                    "'{bad}' is not a number of seconds from 0.1 to 3600"
                ))
            );
        }
    }

    #[test]
    fn parses_sizes_points_and_colors() {
        assert_eq!(size("1280x720"), Ok((1280, 720)));
        assert!(size("1280").is_err());
        assert!(size("ax3").is_err());
        assert_eq!(vec3("1, 2.5,-3"), Ok(DVec3::new(1.0, 2.5, -3.0)));
        assert!(vec3("1,NaN,3").is_err());
        assert!(vec3("1,2").is_err());
        assert_eq!(color("#ff8000"), Ok([255, 128, 0, 255]));
        assert_eq!(color("ff800080"), Ok([255, 128, 0, 128]));
        assert_eq!(color("transparent"), Ok([0, 0, 0, 0]));
        assert!(color("#ff80").is_err());
        let background = Rgba([24, 24, 28, 255]);
        assert_eq!(rgba(&background.to_string()), Ok(background));
        assert_eq!(color_mode("Elevation"), Ok(ColorMode::Elevation));
        let range = |min, max| Ok(ColorRange { min, max });
        assert_eq!(color_range("-12.5..340"), range(-12.5, 340.0));
        assert_eq!(color_range("0 .. 65535"), range(0.0, 65535.0));
        assert_eq!(color_range("-20..-5.25"), range(-20.0, -5.25));
        assert!(
            color_range("NaN..1").is_ok_and(|r| r.min.is_nan()),
            "checked by the request"
        );
        assert!(color_range("1-5").is_err());
        assert!(color_range("a..5").is_err());
        assert_eq!(color_ramp("Turbo"), Ok(ColorRamp::Turbo));
        assert!(color_ramp("jet").is_err_and(|e| e.contains("viridis, inferno, turbo, grey")));
        assert_eq!(color_mode("#010203"), Ok(ColorMode::Fixed([1, 2, 3])));
        assert!(color_mode("rainbow").is_err());
        assert!(positive("0").is_err());
        assert!(positive("inf").is_err());
        assert_eq!(bytes("512MiB"), Ok(512 << 20));
        assert_eq!(bytes("4GiB"), Ok(4 << 30));
        assert_eq!(bytes("1.5G"), Ok(3 << 29));
        assert_eq!(bytes("65536"), Ok(65536));
        assert!(bytes("lots").is_err());
        assert!(bytes("-1G").is_err());
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("NaN").is_err());
    }
}
