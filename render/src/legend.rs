//! The legend of a render's colors: a small image of the ramp with its range's numbers
//! (elevation, intensity), or the swatches of a palette with their names (classification,
//! return number). Drawn with plotters' bitmap backend and a TrueType font from the system
//! (pure Rust; no system libraries), the font the benchmark's plot uses.

use std::path::Path;
use std::sync::OnceLock;

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::color::{
    classification_color, return_color, ColorMode, ColorRamp, ColorRange, Coloring, NAMED_CLASSES,
    NAMED_RETURNS,
};

/// Where the label font is looked for, in order.
pub const FONT_PATHS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Size of a ramp's legend in pixels.
pub const RAMP_LEGEND_SIZE: (u32, u32) = (360, 84);
/// Width of a palette's legend; its height grows with its swatches.
pub const SWATCH_LEGEND_WIDTH: u32 = 260;
/// Height of one swatch's row, and of the title above them.
const ROW: u32 = 22;
const MARGIN: i32 = 12;
const BACKGROUND: RGBColor = WHITE;
/// Interior ticks of a ramp, about.
const TICKS: f64 = 4.0;

#[derive(Debug, thiserror::Error)]
#[error("legend: {0}")]
pub struct LegendError(String);

/// What a legend shows.
#[derive(Debug, Clone, PartialEq)]
pub enum Legend {
    /// A ramp over a range, in the units of `title`'s quantity.
    Ramp {
        title: String,
        ramp: ColorRamp,
        range: ColorRange,
    },
    /// Colors and their names.
    Swatches {
        title: String,
        entries: Vec<([u8; 3], String)>,
    },
}

impl Legend {
    /// The legend of `coloring`, `range` being the range its ramp spans (elevation and
    /// intensity; the request's or the dataset's robust one). `None` where a legend names
    /// nothing: the file's RGB, one fixed color, or a ramp with no range (nothing to color
    /// by).
    pub fn of(coloring: Coloring, range: Option<ColorRange>) -> Option<Self> {
        let swatches = |title: &str, entries: &[(u8, &str)], color: fn(u8) -> u32| {
            Some(Self::Swatches {
                title: title.into(),
                entries: entries
                    .iter()
                    .map(|&(value, name)| {
                        let [r, g, b, _] = color(value).to_le_bytes();
                        ([r, g, b], name.to_string())
                    })
                    .collect(),
            })
        };
        match coloring.mode {
            ColorMode::Elevation | ColorMode::Intensity => Some(Self::Ramp {
                title: coloring.mode.name().into(),
                ramp: coloring.ramp(),
                range: range?,
            }),
            ColorMode::Classification => {
                swatches("classification", &NAMED_CLASSES, classification_color)
            }
            ColorMode::ReturnNumber => swatches("return", &NAMED_RETURNS, return_color),
            ColorMode::Rgb | ColorMode::Fixed(_) => None,
        }
    }

    /// The image's size in pixels.
    pub fn size(&self) -> (u32, u32) {
        match self {
            Self::Ramp { .. } => RAMP_LEGEND_SIZE,
            Self::Swatches { entries, .. } => (
                SWATCH_LEGEND_WIDTH,
                (entries.len() as u32 + 1) * ROW + 2 * MARGIN as u32,
            ),
        }
    }

    /// The legend drawn on white.
    pub fn draw(&self) -> Result<image::RgbImage, LegendError> {
        register_font().map_err(LegendError)?;
        let (width, height) = self.size();
        let mut pixels = vec![0u8; width as usize * height as usize * 3];
        {
            let root = BitMapBackend::with_buffer(&mut pixels, (width, height)).into_drawing_area();
            root.fill(&BACKGROUND).map_err(draw_error)?;
            match self {
                Self::Ramp { title, ramp, range } => draw_ramp(&root, title, *ramp, *range)?,
                Self::Swatches { title, entries } => draw_swatches(&root, title, entries)?,
            }
            root.present().map_err(draw_error)?;
        }
        image::RgbImage::from_raw(width, height, pixels)
            .ok_or_else(|| LegendError("the legend's buffer has the wrong size".into()))
    }

    /// Writes the legend to `path`, in the format its extension names (PNG for `.png`).
    pub fn write(&self, path: &Path) -> Result<(), LegendError> {
        self.draw()?
            .save(path)
            .map_err(|e| LegendError(format!("writing {}: {e}", path.display())))
    }
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

fn draw_error(error: impl std::fmt::Display) -> LegendError {
    LegendError(error.to_string())
}

fn text_style(size: u32) -> TextStyle<'static> {
    ("sans-serif", size).into_font().color(&BLACK)
}

fn draw_ramp(
    root: &Area<'_>,
    title: &str,
    ramp: ColorRamp,
    range: ColorRange,
) -> Result<(), LegendError> {
    let (width, _) = RAMP_LEGEND_SIZE;
    let (left, right) = (MARGIN + 8, width as i32 - MARGIN - 8);
    let (top, bottom) = (MARGIN + 20, MARGIN + 44);
    root.draw(&Text::new(
        title.to_string(),
        (MARGIN, MARGIN - 2),
        text_style(15),
    ))
    .map_err(draw_error)?;
    for x in left..=right {
        let t = (x - left) as f32 / (right - left) as f32;
        let [r, g, b] = ramp.color(t);
        root.draw(&PathElement::new(
            vec![(x, top), (x, bottom)],
            RGBColor(r, g, b),
        ))
        .map_err(draw_error)?;
    }
    root.draw(&Rectangle::new([(left, top), (right, bottom)], BLACK))
        .map_err(draw_error)?;
    let ticks = ticks(range);
    let decimals = ticks.decimals;
    let at = |value: f64| {
        let t = (value - range.min) / (range.max - range.min);
        left + (t * f64::from(right - left)).round() as i32
    };
    for (value, hpos) in std::iter::once((range.min, HPos::Left))
        .chain(ticks.values.iter().map(|&v| (v, HPos::Center)))
        .chain(std::iter::once((range.max, HPos::Right)))
    {
        let x = at(value);
        root.draw(&PathElement::new(vec![(x, bottom), (x, bottom + 5)], BLACK))
            .map_err(draw_error)?;
        let anchor = match hpos {
            HPos::Left => x - 8,
            HPos::Right => x + 8,
            _ => x,
        };
        // The ends are the range's own values: shown as given, to two decimals.
        let decimals = match hpos {
            HPos::Center => decimals,
            _ => decimals.max(2),
        };
        root.draw(&Text::new(
            number(value, decimals),
            (anchor, bottom + 7),
            text_style(13).pos(Pos::new(hpos, VPos::Top)),
        ))
        .map_err(draw_error)?;
    }
    Ok(())
}

fn draw_swatches(
    root: &Area<'_>,
    title: &str,
    entries: &[([u8; 3], String)],
) -> Result<(), LegendError> {
    root.draw(&Text::new(
        title.to_string(),
        (MARGIN, MARGIN),
        text_style(15),
    ))
    .map_err(draw_error)?;
    for (row, ([r, g, b], name)) in entries.iter().enumerate() {
        let y = MARGIN + (row as i32 + 1) * ROW as i32;
        let square = [(MARGIN, y + 3), (MARGIN + 14, y + 17)];
        root.draw(&Rectangle::new(square, RGBColor(*r, *g, *b).filled()))
            .map_err(draw_error)?;
        root.draw(&Rectangle::new(square, BLACK))
            .map_err(draw_error)?;
        root.draw(&Text::new(
            name.clone(),
            (MARGIN + 22, y + 3),
            text_style(13),
        ))
        .map_err(draw_error)?;
    }
    Ok(())
}

/// Round values strictly inside a range, and the decimals that write them.
#[derive(Debug, PartialEq)]
struct Ticks {
    values: Vec<f64>,
    decimals: usize,
}

/// About [`TICKS`] values at a step of 1, 2 or 5 times a power of ten, strictly inside
/// `range` and clear of its ends (whose labels are drawn there).
fn ticks(range: ColorRange) -> Ticks {
    let span = range.max - range.min;
    let raw = span / TICKS;
    let power = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .find(|&s| s >= raw)
        .unwrap_or(10.0 * power);
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let clear = 0.15 * span;
    let mut values = Vec::new();
    let mut value = (range.min / step).ceil() * step;
    while value < range.max {
        if value - range.min > clear && range.max - value > clear {
            values.push(value);
        }
        value += step;
    }
    Ticks { values, decimals }
}

/// `value` with at most `decimals` decimals, no trailing zeros and no negative zero.
fn number(value: f64, decimals: usize) -> String {
    let text = format!("{value:.decimals$}");
    let text = if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    };
    if text == "-0" {
        "0".into()
    } else {
        text
    }
}

/// Registers the first font of [`FONT_PATHS`] found as plotters' "sans-serif", once for the
/// process (plotters keeps fonts for its life).
pub fn register_font() -> Result<(), String> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let (path, bytes) = FONT_PATHS
                .iter()
                .find_map(|p| std::fs::read(p).ok().map(|b| (p, b)))
                .ok_or_else(|| {
                    format!(
                        "no font for the labels: looked for {} (Debian: apt-get install \
                         fonts-dejavu-core)",
                        FONT_PATHS.join(", ")
                    )
                })?;
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                .map_err(|_| format!("{path} is not a usable TrueType font"))
        })
        .clone()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(min: f64, max: f64) -> ColorRange {
        ColorRange { min, max }
    }

    #[test]
    fn ticks_are_round_and_clear_of_the_ends() {
        assert_eq!(
            ticks(range(-12.5, 340.0)),
            Ticks {
                values: vec![100.0, 200.0],
                decimals: 0
            }
        );
        assert_eq!(
            ticks(range(0.0, 1.0)),
            Ticks {
                values: vec![0.5],
                decimals: 1
            }
        );
        assert_eq!(number(-0.0001, 2), "0");
        assert_eq!(number(12.50, 2), "12.5");
        assert_eq!(number(340.0, 0), "340");
    }

    #[test]
    fn legends_of_each_mode() {
        let elevation = Coloring::of_mode(ColorMode::Elevation);
        assert_eq!(Legend::of(elevation, None), None, "nothing to color by");
        let ramp = Legend::of(elevation, Some(range(10.0, 20.0))).expect("a ramp");
        assert_eq!(ramp.size(), RAMP_LEGEND_SIZE);
        let Some(Legend::Swatches { entries, .. }) =
            Legend::of(Coloring::of_mode(ColorMode::Classification), None)
        else {
            panic!("classes have swatches");
        };
        assert_eq!(entries.len(), NAMED_CLASSES.len());
        assert_eq!(entries[1], ([166, 118, 61], "ground".to_string()));
        assert!(Legend::of(Coloring::of_mode(ColorMode::Rgb), None).is_none());
        assert!(Legend::of(Coloring::of_mode(ColorMode::Fixed([1, 2, 3])), None).is_none());
    }

    #[test]
    fn a_legend_draws_its_ramp_and_numbers() {
        let legend = Legend::of(
            Coloring {
                mode: ColorMode::Intensity,
                range: None,
                ramp: Some(ColorRamp::Inferno),
            },
            Some(range(0.0, 4000.0)),
        )
        .expect("a ramp");
        let image = legend.draw().expect("drawn");
        assert_eq!(image.dimensions(), RAMP_LEGEND_SIZE);
        let has = |rgb: [u8; 3]| image.pixels().any(|p| p.0 == rgb);
        assert!(has(ColorRamp::Inferno.color(0.5)), "the ramp's middle");
        assert!(has([0, 0, 0]), "text and frame");
    }
}
