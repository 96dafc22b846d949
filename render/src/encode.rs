//! Encoding rendered frames: a frame's image as PNG bytes, or as a PNG, JPEG, WebP or TIFF
//! file chosen by its extension (a TIFF of an orthographic top view placed on the ground,
//! [`geotiff`]), and its depth image as a 16-bit grey PNG.
//!
//! The renderer returns pixels; encoding them is the caller's choice, and is timed as the
//! frame's "encode" stage so that it still shows in the frame's timings.

pub mod geotiff;
pub mod video;

use std::fs::File;
use std::io::{BufWriter, Cursor, Seek, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use image::codecs::jpeg::JpegEncoder;
use image::codecs::webp::WebPEncoder;
use image::{
    DynamicImage, ExtendedColorType, ImageBuffer, ImageError, ImageFormat, Luma, RgbaImage,
};
use tiff::encoder::{
    colortype, Compression, DeflateLevel, DirectoryEncoder, Predictor, TiffEncoder, TiffKind,
};
use tiff::tags::{ExtraSamples, Tag};

use crate::raster::{Clock, Frame, Stage};
use geotiff::{GeoCrs, Georeference};

/// Why a frame could not be encoded. Callers name the file they were writing.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// A depth PNG was asked of a frame rendered without [`FrameSettings::read_depth`].
    ///
    /// [`FrameSettings::read_depth`]: crate::raster::FrameSettings::read_depth
    #[error("the frame was rendered without its depth image (read_depth)")]
    NoDepthImage,
    /// The encoder or the file system failed.
    #[error("encoding the image: {0}")]
    Image(#[from] ImageError),
    /// The TIFF encoder or the file system failed.
    #[error("encoding the TIFF: {0}")]
    Tiff(#[from] tiff::TiffError),
    /// A file beside a TIFF (its world file, WKT) could not be written or removed.
    #[error("writing {path}: {source}", path = path.display())]
    Sidecar {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file's extension names no format a frame is written in.
    #[error("{0}: give a file ending in {exts}", exts = FrameFormat::EXTENSIONS)]
    UnknownFormat(String),
}

/// The file formats a frame's image is written in, chosen by the file's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    Png,
    /// Baseline JPEG at [`JPEG_QUALITY`]; no alpha channel.
    Jpeg,
    /// Lossless WebP.
    WebP,
    /// RGBA at the frame's 8 bits a channel, alpha declared unassociated, Deflate-compressed;
    /// georeferenced when the frame is an orthographic view from straight above
    /// ([`save_georeferenced_frame`]). Never 16 bits: the renderer resolves colors to 8 bits,
    /// and widened values would only claim a precision the frame does not have.
    Tiff,
}

/// JPEG quality (1 to 100) of [`FrameFormat::Jpeg`]: high enough that the points' edges do
/// not ring.
pub const JPEG_QUALITY: u8 = 92;

impl FrameFormat {
    /// The extensions accepted, for messages.
    pub const EXTENSIONS: &'static str = ".png, .jpg/.jpeg, .webp or .tif/.tiff";

    /// The format a file named `path` is written in, from its extension (any case).
    pub fn from_path(path: &Path) -> Result<Self, EncodeError> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("png") => Ok(Self::Png),
            Some("jpg" | "jpeg") => Ok(Self::Jpeg),
            Some("webp") => Ok(Self::WebP),
            Some("tif" | "tiff") => Ok(Self::Tiff),
            Some(other) => Err(EncodeError::UnknownFormat(format!(
                "{} is not an image format pointfarm writes (.{other})",
                path.display()
            ))),
            None => Err(EncodeError::UnknownFormat(format!(
                "{} has no extension to choose an image format by",
                path.display()
            ))),
        }
    }

    /// Whether the format keeps a transparent background.
    pub fn has_alpha(self) -> bool {
        self != Self::Jpeg
    }

    /// The usual extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Png => "png",
            Self::Jpeg => "jpg",
            Self::WebP => "webp",
            Self::Tiff => "tif",
        }
    }
}

/// Encodes the frame's image as PNG bytes and records the time in its "encode" stage.
pub fn png_bytes(frame: &mut Frame) -> Result<Vec<u8>, EncodeError> {
    timed_encode(frame, |image| {
        let mut png = Vec::new();
        image.write_to(&mut Cursor::new(&mut png), ImageFormat::Png)?;
        Ok(png)
    })
}

/// Writes the frame's image as a file in `format` and records the time in its "encode" stage.
pub fn save_frame(frame: &mut Frame, path: &Path, format: FrameFormat) -> Result<(), EncodeError> {
    save_georeferenced_frame(frame, path, format, None)
}

/// [`save_frame`], a TIFF placed on the ground by `georeference`: GeoTIFF tags (pixel scale
/// and tie point, or the transformation of a rotated view; the EPSG codes of the CRS), and
/// for a CRS known only as WKT its world file, `.prj` and GDAL `.aux.xml` beside it
/// ([`geotiff::sidecar_paths`]). Other formats ignore it.
pub fn save_georeferenced_frame(
    frame: &mut Frame,
    path: &Path,
    format: FrameFormat,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    timed_encode(frame, |image| {
        write_image(image, path, format, georeference)
    })
}

/// Writes an image (a frame's, or one fetched from a server) as a file in `format`.
pub fn save_image(image: &RgbaImage, path: &Path, format: FrameFormat) -> Result<(), EncodeError> {
    write_image(image, path, format, None)
}

fn write_image(
    image: &RgbaImage,
    path: &Path,
    format: FrameFormat,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    match format {
        FrameFormat::Png => Ok(image.save_with_format(path, ImageFormat::Png)?),
        FrameFormat::Jpeg => {
            let rgb = DynamicImage::ImageRgba8(image.clone()).into_rgb8();
            let mut file = BufWriter::new(File::create(path).map_err(ImageError::IoError)?);
            JpegEncoder::new_with_quality(&mut file, JPEG_QUALITY).encode_image(&rgb)?;
            file.flush().map_err(ImageError::IoError)?;
            Ok(())
        }
        FrameFormat::WebP => {
            let mut file = BufWriter::new(File::create(path).map_err(ImageError::IoError)?);
            WebPEncoder::new_lossless(&mut file).encode(
                image.as_raw(),
                image.width(),
                image.height(),
                ExtendedColorType::Rgba8,
            )?;
            file.flush().map_err(ImageError::IoError)?;
            Ok(())
        }
        FrameFormat::Tiff => write_tiff(image, path, georeference),
    }
}

/// Writes `image` as an RGBA TIFF, 8 bits a channel with the alpha declared unassociated,
/// Deflate-compressed after horizontal differencing, with `georeference`'s tags and files.
fn write_tiff(
    image: &RgbaImage,
    path: &Path,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    let mut encoder = tiff_encoder(path)?;
    let mut tiff = encoder.new_image::<colortype::RGBA8>(image.width(), image.height())?;
    // The RGBA color type counts four samples but does not say what the fourth is.
    tiff.encoder().write_tag(
        Tag::ExtraSamples,
        &[ExtraSamples::UnassociatedAlpha.to_u16()][..],
    )?;
    write_georeference_tags(tiff.encoder(), georeference)?;
    tiff.write_data(image.as_raw())?;
    write_georeference_sidecars(path, georeference)
}

/// A TIFF encoder writing to a new file at `path`, Deflate after horizontal differencing.
fn tiff_encoder(path: &Path) -> Result<TiffEncoder<BufWriter<File>>, EncodeError> {
    let file = BufWriter::new(File::create(path).map_err(ImageError::IoError)?);
    Ok(TiffEncoder::new(file)?
        .with_compression(Compression::Deflate(DeflateLevel::Balanced))
        .with_predictor(Predictor::Horizontal))
}

/// The GeoTIFF tags of `georeference`: pixel scale and tie point for a north-up map, else
/// its transformation, and the key directory of its CRS.
fn write_georeference_tags<W: Write + Seek, K: TiffKind>(
    tags: &mut DirectoryEncoder<'_, W, K>,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    let Some(georeference) = georeference else {
        return Ok(());
    };
    let map = &georeference.transform;
    if map.is_north_up() {
        let scale = [map.per_column.x, -map.per_row.y, 0.0];
        tags.write_tag(Tag::ModelPixelScaleTag, &scale[..])?;
        let tie_point = [0.0, 0.0, 0.0, map.origin.x, map.origin.y, 0.0];
        tags.write_tag(Tag::ModelTiepointTag, &tie_point[..])?;
    } else {
        tags.write_tag(Tag::ModelTransformationTag, &map.model_transformation()[..])?;
    }
    tags.write_tag(
        Tag::GeoKeyDirectoryTag,
        &georeference.crs.key_directory()[..],
    )?;
    Ok(())
}

/// The world file, `.prj` and GDAL `.aux.xml` beside the TIFF at `path` when its CRS is known
/// only as WKT, which no GeoTIFF key holds; otherwise those an earlier image of that name left
/// are removed, since GDAL would place the new image by them.
fn write_georeference_sidecars(
    path: &Path,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    let texts = match georeference {
        Some(Georeference {
            transform,
            crs: GeoCrs::Wkt(wkt),
        }) => Some([
            transform.world_file(),
            format!("{wkt}\n"),
            geotiff::aux_xml(wkt),
        ]),
        _ => None,
    };
    for (at, sidecar) in geotiff::sidecar_paths(path).into_iter().enumerate() {
        let done = match &texts {
            Some(texts) => std::fs::write(&sidecar, &texts[at]),
            None => match std::fs::remove_file(&sidecar) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
                removed => removed,
            },
        };
        done.map_err(|source| EncodeError::Sidecar {
            path: sidecar,
            source,
        })?;
    }
    Ok(())
}

/// Writes the frame's depth image as a 16-bit grey PNG: linear depth from `near` (1) to `far`
/// (65535); 0 where no point landed. Needs [`FrameSettings::read_depth`].
///
/// [`FrameSettings::read_depth`]: crate::raster::FrameSettings::read_depth
pub fn save_depth_png16(
    frame: &Frame,
    path: &Path,
    near: f64,
    far: f64,
) -> Result<(), EncodeError> {
    let pixels = depth_levels(frame, near, far)?;
    let image = ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(
        frame.image.width(),
        frame.image.height(),
        pixels,
    )
    .ok_or_else(|| {
        ImageError::Parameter(image::error::ParameterError::from_kind(
            image::error::ParameterErrorKind::DimensionMismatch,
        ))
    })?;
    Ok(image.save_with_format(path, ImageFormat::Png)?)
}

/// GDAL's TIFF tag of band metadata (XML), where it reads a band's scale and offset.
const GDAL_METADATA_TAG: u16 = 42112;

/// Writes the frame's depth image as a 16-bit grey TIFF, with the levels of
/// [`save_depth_png16`] (0, no point, declared GDAL's no-data value; the scale and offset that
/// turn a level into its distance in GDAL's metadata), Deflate-compressed and
/// placed by `georeference` as [`save_georeferenced_frame`] places a frame: the 16 bits a GIS
/// tool reads of a top view, where depth is the height below the camera.
pub fn save_depth_tiff16(
    frame: &Frame,
    path: &Path,
    near: f64,
    far: f64,
    georeference: Option<&Georeference>,
) -> Result<(), EncodeError> {
    let levels = depth_levels(frame, near, far)?;
    let mut encoder = tiff_encoder(path)?;
    let (width, height) = frame.image.dimensions();
    let mut tiff = encoder.new_image::<colortype::Gray16>(width, height)?;
    tiff.encoder().write_tag(Tag::GdalNodata, "0")?;
    // GDAL's scale and offset turn a level back into its distance, as the sidecar says.
    let scale = (far - near).max(f64::MIN_POSITIVE) / 65534.0;
    let metadata = format!(
        "<GDALMetadata>\n\
         <Item name=\"DESCRIPTION\" sample=\"0\" role=\"description\">depth</Item>\n\
         <Item name=\"SCALE\" sample=\"0\" role=\"scale\">{scale:e}</Item>\n\
         <Item name=\"OFFSET\" sample=\"0\" role=\"offset\">{offset:e}</Item>\n\
         </GDALMetadata>",
        offset = near - scale,
    );
    tiff.encoder()
        .write_tag(Tag::Unknown(GDAL_METADATA_TAG), metadata.as_str())?;
    write_georeference_tags(tiff.encoder(), georeference)?;
    tiff.write_data(&levels)?;
    write_georeference_sidecars(path, georeference)
}

/// The depth image's 16-bit levels: linear from `near` (1) to `far` (65535), 0 where no point
/// landed.
fn depth_levels(frame: &Frame, near: f64, far: f64) -> Result<Vec<u16>, EncodeError> {
    let Some(depth) = &frame.depth else {
        return Err(EncodeError::NoDepthImage);
    };
    let span = (far - near).max(f64::MIN_POSITIVE);
    Ok(depth
        .iter()
        .map(|&d| {
            if d.is_finite() {
                1 + (((d as f64 - near) / span).clamp(0.0, 1.0) * 65534.0).round() as u16
            } else {
                0
            }
        })
        .collect())
}

/// Runs `encode` on the frame's image, timing it as the frame's "encode" stage.
fn timed_encode<T>(
    frame: &mut Frame,
    encode: impl FnOnce(&RgbaImage) -> Result<T, EncodeError>,
) -> Result<T, EncodeError> {
    let started = Instant::now();
    let encoded = encode(&frame.image)?;
    frame.timings.push(
        Stage::Encode,
        started.elapsed().as_secs_f64() * 1e3,
        Clock::Host,
    );
    Ok(encoded)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{AtomicsPath, StageTimings};

    fn gradient_frame() -> Frame {
        let image = RgbaImage::from_fn(64, 48, |x, y| {
            image::Rgba([
                (x * 4) as u8,
                (y * 5) as u8,
                128,
                if x < 4 { 0 } else { 255 },
            ])
        });
        Frame {
            image,
            depth: None,
            timings: StageTimings::default(),
            atomics: AtomicsPath::Atomic64,
            gain: None,
        }
    }

    #[test]
    fn every_format_reads_back_as_the_frame_it_was_written_from() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (name, format) in [
            ("f.png", FrameFormat::Png),
            ("f.WEBP", FrameFormat::WebP),
            ("f.tiff", FrameFormat::Tiff),
            ("f.jpeg", FrameFormat::Jpeg),
        ] {
            let path = dir.path().join(name);
            assert_eq!(FrameFormat::from_path(&path).expect("known"), format);
            let mut frame = gradient_frame();
            save_frame(&mut frame, &path, format).expect("written");
            assert!(frame.timings.get(Stage::Encode).is_some(), "{name}: timed");
            let read = image::open(&path).expect("readable");
            if format == FrameFormat::Tiff {
                // The frame's own 8 bits, never widened.
                let rgba = read.as_rgba8().expect("8-bit RGBA");
                assert_eq!(rgba, &gradient_frame().image, "{name}");
            } else if format == FrameFormat::Jpeg {
                // Lossy and opaque: close in color, alpha dropped.
                let rgb = read.to_rgb8();
                let worst = rgb
                    .pixels()
                    .zip(gradient_frame().image.pixels())
                    .flat_map(|(a, e)| a.0.into_iter().zip(e.0).map(|(a, e)| a.abs_diff(e)))
                    .max();
                assert!(worst.is_some_and(|w| w <= 12), "{name}: {worst:?}");
            } else {
                assert_eq!(read.to_rgba8(), gradient_frame().image, "{name}");
            }
        }
    }

    /// The TIFF at `path`'s tag `tag` as unsigned integers, or as doubles.
    fn tiff_tag(path: &Path, tag: Tag) -> Option<tiff::decoder::ifd::Value> {
        let file = std::io::BufReader::new(File::open(path).expect("open"));
        let mut decoder = tiff::decoder::Decoder::new(file).expect("a TIFF");
        decoder.find_tag(tag).expect("readable tags")
    }

    #[test]
    fn a_tiff_is_compressed_with_its_alpha_declared() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("f.tif");
        save_frame(&mut gradient_frame(), &path, FrameFormat::Tiff).expect("written");
        let value = |tag| tiff_tag(&path, tag).map(|v| v.into_u16_vec().expect("shorts"));
        assert_eq!(
            value(Tag::ExtraSamples),
            Some(vec![2]),
            "unassociated alpha"
        );
        assert_eq!(value(Tag::Compression), Some(vec![8]), "Deflate");
        assert_eq!(value(Tag::BitsPerSample), Some(vec![8; 4]));
        assert_eq!(value(Tag::GeoKeyDirectoryTag), None, "not placed");
    }

    #[test]
    fn a_georeferenced_tiff_carries_its_map_and_epsg_code_or_its_wkt_beside_it() {
        use geotiff::{CrsKind, GeoTransform};
        use glam::DVec2;
        let dir = tempfile::tempdir().expect("tempdir");
        let transform = GeoTransform {
            origin: DVec2::new(637_000.5, 851_064.25),
            per_column: DVec2::new(0.5, 0.0),
            per_row: DVec2::new(0.0, -0.5),
        };
        let epsg = Georeference {
            transform,
            crs: GeoCrs::Epsg {
                kind: CrsKind::Projected,
                code: 2992,
                vertical: None,
            },
        };
        let path = dir.path().join("epsg.tif");
        save_georeferenced_frame(&mut gradient_frame(), &path, FrameFormat::Tiff, Some(&epsg))
            .expect("written");
        let doubles = |tag| tiff_tag(&path, tag).map(|v| v.into_f64_vec().expect("doubles"));
        assert_eq!(doubles(Tag::ModelPixelScaleTag), Some(vec![0.5, 0.5, 0.0]));
        assert_eq!(
            doubles(Tag::ModelTiepointTag),
            Some(vec![0.0, 0.0, 0.0, 637_000.5, 851_064.25, 0.0])
        );
        let keys = tiff_tag(&path, Tag::GeoKeyDirectoryTag)
            .map(|v| v.into_u16_vec().expect("shorts"))
            .expect("keys");
        assert!(
            keys.chunks(4).any(|key| key == [3072, 0, 1, 2992]),
            "{keys:?}"
        );
        assert_eq!(
            image::open(&path).expect("readable").to_rgba8(),
            gradient_frame().image
        );
        assert!(geotiff::sidecar_paths(&path).iter().all(|p| !p.exists()));

        let wkt = "PROJCS[\"Lambert <ft>\",UNIT[\"foot\",0.3048]]";
        let only_wkt = Georeference {
            transform,
            crs: GeoCrs::Wkt(wkt.to_owned()),
        };
        let path = dir.path().join("wkt.tif");
        save_georeferenced_frame(
            &mut gradient_frame(),
            &path,
            FrameFormat::Tiff,
            Some(&only_wkt),
        )
        .expect("written");
        let [world, prj, aux] = geotiff::sidecar_paths(&path);
        let read = |p: &Path| std::fs::read_to_string(p).expect("sidecar");
        assert_eq!(read(&prj).trim(), wkt);
        assert!(read(&aux).contains("Lambert &lt;ft&gt;"), "{}", read(&aux));
        let lines: Vec<f64> = read(&world)
            .lines()
            .map(|l| l.parse().expect("number"))
            .collect();
        assert_eq!(lines, [0.5, 0.0, 0.0, -0.5, 637_000.75, 851_064.0]);

        // An image written over it without a place takes none from the old one's files.
        save_frame(&mut gradient_frame(), &path, FrameFormat::Tiff).expect("written");
        assert!(![world, prj, aux].iter().any(|p| p.exists()));
    }

    #[test]
    fn a_depth_tiff_holds_the_depth_png_levels_in_16_bits() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut frame = gradient_frame();
        // Every level from near to far, and pixels without a point.
        let (width, height) = frame.image.dimensions();
        frame.depth = Some(
            (0..width * height)
                .map(|i| match i % 7 {
                    0 => f32::INFINITY,
                    _ => 10.0 + 90.0 * i as f32 / (width * height) as f32,
                })
                .collect(),
        );
        let (png, tiff) = (dir.path().join("d.png"), dir.path().join("d.tif"));
        save_depth_png16(&frame, &png, 10.0, 100.0).expect("png");
        save_depth_tiff16(&frame, &tiff, 10.0, 100.0, None).expect("tiff");
        let levels = depth_levels(&frame, 10.0, 100.0).expect("depth");
        assert!(levels.contains(&0) && levels.iter().any(|&l| l > 60_000));
        let read = image::open(&tiff).expect("readable");
        let gray = read.as_luma16().expect("16-bit grey");
        assert_eq!(gray.as_raw(), &levels);
        let png = image::open(&png).expect("readable");
        assert_eq!(png.as_luma16().expect("16-bit grey"), gray);
        let value = |tag| tiff_tag(&tiff, tag);
        assert_eq!(
            value(Tag::BitsPerSample).map(|v| v.into_u16_vec().expect("shorts")),
            Some(vec![16])
        );
        let nodata = value(Tag::GdalNodata).map(|v| v.into_string().expect("text"));
        assert_eq!(nodata.as_deref(), Some("0"));
        let metadata = value(Tag::Unknown(GDAL_METADATA_TAG))
            .map(|v| v.into_string().expect("text"))
            .expect("GDAL metadata");
        assert!(metadata.contains("role=\"scale\""), "{metadata}");
    }

    #[test]
    fn a_file_without_a_known_extension_is_refused_naming_the_formats() {
        for name in ["frame.bmp", "frame", "frames/"] {
            let error = FrameFormat::from_path(Path::new(name)).expect_err(name);
            let message = error.to_string();
            assert!(message.contains(".jpg/.jpeg"), "{message}");
        }
    }
}
