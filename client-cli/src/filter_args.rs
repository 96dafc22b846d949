//! `pointfarm render`'s filter flags and the [`PointFilter`] they describe.

use clap::Args;
use pointfarm_render::classification::class_code;
use pointfarm_render::cloud::MAX_COORDINATE;
use pointfarm_render::filter::{ClipBox, CodeSet, IntensityRange, PointFilter, MAX_RETURN_NUMBER};

#[derive(Args, Debug, Clone, Default)]
pub struct FilterArgs {
    /// Draw only these classes: ASPRS codes or names, comma-separated (`2,6` or
    /// `ground,building`; names: never-classified, unclassified, ground, low-vegetation,
    /// medium-vegetation, high-vegetation, building, low-noise, model-key-point, water, rail,
    /// road-surface, overlap, wire-guard, wire-conductor, transmission-tower, wire-connector,
    /// bridge-deck, high-noise). Keeps the camera of the whole dataset.
    #[arg(long, value_name = "LIST", value_parser = class_list, conflicts_with = "exclude_classes")]
    classes: Option<CodeSet>,
    /// Draw every class but these (`low-noise,high-noise` hides noise).
    #[arg(long, value_name = "LIST", value_parser = class_list)]
    exclude_classes: Option<CodeSet>,
    /// Draw only these return numbers, comma-separated (`1` for first returns).
    #[arg(long, value_name = "LIST", value_parser = return_list)]
    returns: Option<CodeSet>,
    /// Draw only raw intensities in MIN..MAX, both kept; either end may be left out
    /// (`100..`, `..4000`).
    #[arg(long, value_name = "MIN..MAX", value_parser = intensity_range)]
    intensity: Option<IntensityRange>,
    /// Draw only points inside this box, in the files' coordinates:
    /// `MINX,MINY,MINZ..MAXX,MAXY,MAXZ`, or `MINX,MINY..MAXX,MAXY` for every height. The
    /// automatic camera frames the box's part of the dataset.
    #[arg(long, value_name = "MIN..MAX", value_parser = clip_box, allow_hyphen_values = true)]
    clip: Option<ClipBox>,
}

impl FilterArgs {
    pub fn filter(&self) -> PointFilter {
        PointFilter {
            classes: self
                .classes
                .or(self.exclude_classes.map(|set| set.complement())),
            return_numbers: self.returns,
            intensity: self.intensity,
            clip: self.clip,
        }
    }
}

/// `LIST` of codes or names, each a number or an ASPRS name.
fn class_list(s: &str) -> Result<CodeSet, String> {
    code_list(s, "class", u8::MAX, class_code)
}

fn return_list(s: &str) -> Result<CodeSet, String> {
    code_list(s, "return number", MAX_RETURN_NUMBER, |_| None)
}

fn code_list(
    s: &str,
    what: &str,
    max: u8,
    by_name: impl Fn(&str) -> Option<u8>,
) -> Result<CodeSet, String> {
    let mut codes = Vec::new();
    for item in s.split(',').map(str::trim) {
        if item.is_empty() {
            return Err(format!(
                "expected a comma-separated list of {what}s, got '{s}'"
            ));
        }
        let code = match item.parse::<u32>() {
            Ok(code) => u8::try_from(code)
                .ok()
                .filter(|&code| code <= max)
                .ok_or_else(|| format!("{what} {code} is invalid: it must be 0 to {max}"))?,
            Err(_) => by_name(item).ok_or_else(|| format!("'{item}' is not a {what}"))?,
        };
        codes.push(code);
    }
    Ok(CodeSet::of(codes))
}

/// `MIN..MAX` with either end optional.
fn intensity_range(s: &str) -> Result<IntensityRange, String> {
    let (min, max) = s
        .split_once("..")
        .ok_or_else(|| format!("expected MIN..MAX, e.g. 100..4000, got '{s}'"))?;
    let end = |text: &str, missing: u16| {
        let text = text.trim();
        if text.is_empty() {
            return Ok(missing);
        }
        text.parse::<u16>()
            .map_err(|_| format!("intensity '{text}' is invalid: it must be 0 to 65535"))
    };
    let range = IntensityRange {
        min: end(min, 0)?,
        max: end(max, u16::MAX)?,
    };
    if range.min > range.max {
        return Err(format!("{s} is empty: its minimum is above its maximum"));
    }
    Ok(range)
}

/// `MINX,MINY,MINZ..MAXX,MAXY,MAXZ` or, for every height, `MINX,MINY..MAXX,MAXY`.
fn clip_box(s: &str) -> Result<ClipBox, String> {
    let usage =
        || format!("expected MINX,MINY,MINZ..MAXX,MAXY,MAXZ or MINX,MINY..MAXX,MAXY, got '{s}'");
    let (min, max) = s.split_once("..").ok_or_else(usage)?;
    let corner = |text: &str| -> Result<Vec<f64>, String> {
        text.split(',')
            .map(|v| {
                let v = v.trim();
                v.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| format!("'{v}' is not a finite number"))
            })
            .collect()
    };
    let (min, max) = (corner(min)?, corner(max)?);
    let (min, max) = match (min.as_slice(), max.as_slice()) {
        (&[x0, y0, z0], &[x1, y1, z1]) => ([x0, y0, z0], [x1, y1, z1]),
        (&[x0, y0], &[x1, y1]) => ([x0, y0, -MAX_COORDINATE], [x1, y1, MAX_COORDINATE]),
        _ => return Err(usage()),
    };
    for (axis, (lo, hi)) in ["x", "y", "z"].iter().zip(min.iter().zip(&max)) {
        if lo >= hi {
            return Err(format!(
                "the box is empty along {axis}: {lo} is not below {hi}"
            ));
        }
    }
    Ok(ClipBox { min, max })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classes_by_code_and_name() {
        assert_eq!(class_list("2, 6").expect("valid").codes(), vec![2, 6]);
        assert_eq!(
            class_list("ground,high-vegetation,Building")
                .expect("valid")
                .codes(),
            vec![2, 5, 6]
        );
        assert!(class_list("ground,,6").is_err());
        let error = class_list("256").expect_err("refused");
        assert!(error.contains("must be 0 to 255"), "{error}");
        let error = class_list("trees").expect_err("refused");
        assert!(error.contains("'trees' is not a class"), "{error}");
        assert_eq!(return_list("1,2").expect("valid").codes(), vec![1, 2]);
        assert!(return_list("16")
            .expect_err("refused")
            .contains("must be 0 to 15"));
        assert!(return_list("first").is_err());
    }

    #[test]
    fn excluded_classes_are_the_complement() {
        let args = FilterArgs {
            exclude_classes: Some(class_list("low-noise,high-noise").expect("valid")),
            ..Default::default()
        };
        let classes = args.filter().classes.expect("a set");
        assert!(!classes.contains(7) && !classes.contains(18));
        assert!(classes.contains(2) && classes.contains(255));
    }

    #[test]
    fn intensity_ranges_with_open_ends() {
        assert_eq!(
            intensity_range("100..4000").expect("valid"),
            IntensityRange {
                min: 100,
                max: 4000
            }
        );
        assert_eq!(intensity_range("100..").expect("valid").max, u16::MAX);
        assert_eq!(intensity_range("..40").expect("valid").min, 0);
        assert!(intensity_range("400..100")
            .expect_err("refused")
            .contains("is empty"));
        assert!(intensity_range("70000..").is_err());
        assert!(intensity_range("100").is_err());
    }

    #[test]
    fn clip_boxes_in_three_and_two_dimensions() {
        let b = clip_box("637000.5,851000,-10..637100,851100.25,400").expect("valid");
        assert_eq!(b.min, [637000.5, 851000.0, -10.0]);
        assert_eq!(b.max, [637100.0, 851100.25, 400.0]);
        let flat = clip_box("-5,-5..5,5").expect("valid");
        assert_eq!(flat.min[2], -MAX_COORDINATE);
        assert_eq!(flat.max[2], MAX_COORDINATE);
        assert!(clip_box("1,2,3..4,5").is_err());
        assert!(clip_box("0,0..nan,1")
            .expect_err("refused")
            .contains("finite"));
        assert!(clip_box("5,0..1,1")
            .expect_err("refused")
            .contains("empty along x"));
    }
}
