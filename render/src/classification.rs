//! The ASPRS standard classes by code and by name, for people: `info`'s histograms, the
//! class filter's names, legends.

/// Codes 0 to 18 by their ASPRS names (8 and 12 as LAS 1.1–1.3 name them; 1.4 reserves both).
const NAMES: [&str; 19] = [
    "never classified",
    "unclassified",
    "ground",
    "low vegetation",
    "medium vegetation",
    "high vegetation",
    "building",
    "low noise",
    "model key point",
    "water",
    "rail",
    "road surface",
    "overlap",
    "wire guard",
    "wire conductor",
    "transmission tower",
    "wire connector",
    "bridge deck",
    "high noise",
];

/// The ASPRS name of a standard class, `None` for the reserved and user-defined codes.
pub fn class_name(code: u8) -> Option<&'static str> {
    NAMES.get(usize::from(code)).copied()
}

/// The code of a standard class named as [`class_name`] does, ignoring case, with `-` or `_`
/// for spaces (`low-vegetation`, `ROAD_SURFACE`).
pub fn class_code(name: &str) -> Option<u8> {
    let wanted = name.trim().to_ascii_lowercase().replace(['-', '_'], " ");
    NAMES
        .iter()
        .position(|n| *n == wanted)
        .and_then(|code| u8::try_from(code).ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_codes_round_trip() {
        for code in 0..=18 {
            let name = class_name(code).expect("standard");
            assert_eq!(class_code(name), Some(code));
        }
        assert_eq!(class_code("Low-Vegetation"), Some(3));
        assert_eq!(class_code("high_noise"), Some(18));
        assert_eq!(class_name(19), None);
        assert_eq!(class_code("grounds"), None);
    }
}
