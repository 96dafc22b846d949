//! LAS 1.4's extra bytes VLR (`LASF_Spec` record 4): one 192-byte descriptor per attribute a
//! point record carries after its format's fields, in the order they lie there. Read for
//! `pointfarm info` (the names) and for COPC files (where a pointfarm export keeps each
//! point's weight); written by the COPC export.

/// The VLR's user id and record id.
pub const USER_ID: &str = "LASF_Spec";
pub const RECORD_ID: u16 = 4;
/// Bytes of one descriptor.
pub const DESCRIPTOR_BYTES: usize = 192;
/// Descriptor data type 5: an unsigned 32-bit integer.
pub const DATA_TYPE_U32: u8 = 5;

const DATA_TYPE: usize = 2;
const OPTIONS: usize = 3;
const NAME: std::ops::Range<usize> = 4..36;
const DESCRIPTION: std::ops::Range<usize> = 160..192;

/// One attribute: its name, data type and options (for data type 0, its size in bytes).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExtraByte {
    pub name: String,
    pub data_type: u8,
    pub options: u8,
}

impl ExtraByte {
    /// Bytes the attribute takes in a record; `None` for a data type LAS 1.4 does not define.
    pub fn bytes(&self) -> Option<usize> {
        const ELEMENT: [usize; 10] = [1, 1, 2, 2, 4, 4, 8, 8, 4, 8];
        match self.data_type {
            0 => Some(usize::from(self.options)),
            // 1 to 10 one element, 11 to 20 two (deprecated), 21 to 30 three (deprecated).
            t @ 1..=30 => {
                let t = usize::from(t - 1);
                Some(ELEMENT[t % 10] * (t / 10 + 1))
            }
            _ => None,
        }
    }
}

/// The descriptors of the VLR's `data`; a descriptor cut short is left out.
pub fn parse(data: &[u8]) -> Vec<ExtraByte> {
    data.chunks_exact(DESCRIPTOR_BYTES)
        .map(|d| {
            let name = &d[NAME];
            let end = name.iter().position(|&b| b == 0).unwrap_or(name.len());
            ExtraByte {
                name: String::from_utf8_lossy(&name[..end]).trim().to_owned(),
                data_type: d[DATA_TYPE],
                options: d[OPTIONS],
            }
        })
        .collect()
}

/// Where the attribute `name` of type `data_type` starts within the extra bytes, when every
/// attribute before it has a known size.
pub fn offset_of(descriptors: &[ExtraByte], name: &str, data_type: u8) -> Option<usize> {
    let mut at = 0;
    for d in descriptors {
        if d.name == name {
            return (d.data_type == data_type && d.options == 0).then_some(at);
        }
        at += d.bytes()?;
    }
    None
}

/// A descriptor of a plain attribute (no scale, offset, limits or no-data value).
pub fn descriptor(name: &str, data_type: u8, description: &str) -> [u8; DESCRIPTOR_BYTES] {
    let mut out = [0u8; DESCRIPTOR_BYTES];
    out[DATA_TYPE] = data_type;
    let copy = |field: &mut [u8], text: &str| {
        let n = text.len().min(field.len());
        field[..n].copy_from_slice(&text.as_bytes()[..n]);
    };
    copy(&mut out[NAME], name);
    copy(&mut out[DESCRIPTION], description);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_attribute_is_found_after_the_ones_before_it() {
        let mut data = Vec::new();
        data.extend(descriptor("amplitude", 3, "u16"));
        data.extend(descriptor("normal", 29, "three f32"));
        data.extend(descriptor("weight", DATA_TYPE_U32, "u32"));
        data.extend([0u8; 100]);
        let parsed = parse(&data);
        assert_eq!(parsed.len(), 3);
        assert_eq!(parsed[1].bytes(), Some(12));
        assert_eq!(offset_of(&parsed, "weight", DATA_TYPE_U32), Some(14));
        assert_eq!(offset_of(&parsed, "weight", 6), None, "another type");
        assert_eq!(offset_of(&parsed, "missing", DATA_TYPE_U32), None);
        let unknown = [descriptor("odd", 31, ""), descriptor("weight", 5, "")].concat();
        assert_eq!(offset_of(&parse(&unknown), "weight", 5), None);
    }

    #[test]
    fn the_deprecated_tuple_types_have_their_sizes() {
        let size = |data_type| {
            ExtraByte {
                name: String::new(),
                data_type,
                options: 0,
            }
            .bytes()
        };
        assert_eq!(size(5), Some(4), "u32");
        assert_eq!(size(7), Some(8), "u64");
        assert_eq!(size(9), Some(4), "f32");
        assert_eq!(size(11), Some(2), "two u8");
        assert_eq!(size(19), Some(8), "two f32");
        assert_eq!(size(20), Some(16), "two f64");
        assert_eq!(size(21), Some(3), "three u8");
        assert_eq!(size(30), Some(24), "three f64");
        assert_eq!(size(31), None);
    }
}
