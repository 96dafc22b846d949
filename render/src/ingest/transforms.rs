//! The header's scale factors and offsets, checked before any point is decoded: a NaN,
//! infinite, zero or denormal scale, or a non-finite offset, cannot place points (they
//! would all collapse onto one coordinate or become NaN and only fail much later, at the
//! camera), so each is an error naming the field.

use std::path::Path;

use super::IngestError;

/// Fails on the first unusable scale factor or offset, naming it (`x scale factor is NaN`).
pub(super) fn check_transforms(path: &Path, raw: &las::raw::Header) -> Result<(), IngestError> {
    let scales = [
        ("x scale factor", raw.x_scale_factor),
        ("y scale factor", raw.y_scale_factor),
        ("z scale factor", raw.z_scale_factor),
    ];
    let offsets = [
        ("x offset", raw.x_offset),
        ("y offset", raw.y_offset),
        ("z offset", raw.z_offset),
    ];
    let bad = |field, problem| IngestError::BadTransform {
        path: path.to_owned(),
        field,
        problem,
    };
    for (field, scale) in scales {
        if let Some(problem) = scale_problem(scale) {
            return Err(bad(field, problem));
        }
    }
    for (field, offset) in offsets {
        if let Some(problem) = non_finite(offset) {
            return Err(bad(field, problem));
        }
    }
    Ok(())
}

/// Why a scale factor cannot be used, if it cannot.
fn scale_problem(scale: f64) -> Option<&'static str> {
    non_finite(scale).or(if scale == 0.0 {
        Some("zero")
    } else if !scale.is_normal() {
        Some("denormal")
    } else {
        None
    })
}

fn non_finite(value: f64) -> Option<&'static str> {
    if value.is_nan() {
        Some("NaN")
    } else if value.is_infinite() {
        Some("infinite")
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use std::fs;

    use crate::ingest::test_files::*;
    use crate::ingest::IngestError;

    #[test]
    fn unusable_scales_and_offsets_are_errors_naming_the_field() {
        let dir = tempfile::tempdir().expect("temp dir");
        let cases = [
            (0, f64::NAN, "x scale factor is NaN"),
            (1, 0.0, "y scale factor is zero"),
            (2, f64::MIN_POSITIVE / 4.0, "z scale factor is denormal"),
            (2, f64::NEG_INFINITY, "z scale factor is infinite"),
            (3, f64::INFINITY, "x offset is infinite"),
            (5, f64::NAN, "z offset is NaN"),
        ];
        for name in ["bad_transform.las", "bad_transform.laz"] {
            let (path, original) = file_to_cut(dir.path(), name, 100);
            for (field, value, expected) in cases {
                let mut bytes = original.clone();
                bytes[X_SCALE_OFFSET + 8 * field..][..8].copy_from_slice(&value.to_le_bytes());
                fs::write(&path, &bytes).expect("patch");
                let error = load_error(&path);
                assert!(
                    matches!(error, IngestError::BadTransform { .. })
                        && error.to_string().ends_with(expected),
                    "{error}"
                );
            }
        }
    }

    #[test]
    fn a_huge_scale_that_puts_points_beyond_any_survey_is_an_error() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, mut bytes) = file_to_cut(dir.path(), "huge_scale.las", 100);
        for scale in [1e305, 1e300, 1e12] {
            bytes[X_SCALE_OFFSET..][..8].copy_from_slice(&f64::to_le_bytes(scale));
            fs::write(&path, &bytes).expect("patch");
            let error = load_error(&path);
            assert!(
                matches!(error, IngestError::ImplausibleCoordinates { .. }),
                "{error}"
            );
        }
    }
}
