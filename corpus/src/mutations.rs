//! The mutations of one source: truncations, header, VLR, EVLR, LASzip VLR and chunk table
//! fields set to extremes, and seeded byte flips in the header, the VLRs and the points.
//! Each mutant is marked `headline` when it is one of the extremes every run must cover
//! (the fast subset is made of those).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::layout::{header, Layout, Record, EVLR_HEADER_LEN};
use crate::sources::Source;
use crate::CorpusError;

/// What a mutation changes; the runner counts outcomes per kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Kind {
    Truncate,
    HeaderField,
    VlrField,
    EvlrField,
    LaszipField,
    ChunkTable,
    FlipHeader,
    FlipVlrs,
    FlipPoints,
}

impl Kind {
    pub const ALL: [Kind; 9] = [
        Kind::Truncate,
        Kind::HeaderField,
        Kind::VlrField,
        Kind::EvlrField,
        Kind::LaszipField,
        Kind::ChunkTable,
        Kind::FlipHeader,
        Kind::FlipVlrs,
        Kind::FlipPoints,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Kind::Truncate => "truncate",
            Kind::HeaderField => "header",
            Kind::VlrField => "vlr",
            Kind::EvlrField => "evlr",
            Kind::LaszipField => "laszip",
            Kind::ChunkTable => "chunks",
            Kind::FlipHeader => "flip-header",
            Kind::FlipVlrs => "flip-vlrs",
            Kind::FlipPoints => "flip-points",
        }
    }

    pub fn from_label(label: &str) -> Option<Kind> {
        Kind::ALL.into_iter().find(|kind| kind.label() == label)
    }
}

/// One mutated file.
pub struct Mutant {
    pub kind: Kind,
    pub detail: String,
    pub headline: bool,
    pub bytes: Vec<u8>,
}

/// The width of a patched field.
#[derive(Clone, Copy)]
enum Width {
    U8,
    U16,
    U32,
    U64,
    F64,
}

impl Width {
    fn bytes(self) -> usize {
        match self {
            Width::U8 => 1,
            Width::U16 => 2,
            Width::U32 => 4,
            Width::U64 | Width::F64 => 8,
        }
    }

    fn max(self) -> u64 {
        match self {
            Width::U8 => u8::MAX.into(),
            Width::U16 => u16::MAX.into(),
            Width::U32 => u32::MAX.into(),
            Width::U64 | Width::F64 => u64::MAX,
        }
    }
}

/// A value written into a field.
#[derive(Clone, Copy)]
enum Value {
    Int(u64),
    Float(f64),
}

/// Collects the mutants of one source, dropping those equal to the source or to an earlier one.
struct Mutants<'a> {
    source: &'a [u8],
    list: Vec<Mutant>,
}

impl Mutants<'_> {
    fn push(&mut self, kind: Kind, detail: String, headline: bool, bytes: Vec<u8>) {
        let duplicate = bytes == self.source
            || self
                .list
                .iter()
                .any(|other| other.kind == kind && other.bytes == bytes);
        if !duplicate {
            self.list.push(Mutant {
                kind,
                detail,
                headline,
                bytes,
            });
        }
    }

    /// The source with one field set; nothing when the field lies outside the file.
    fn patched(&self, at: usize, width: Width, value: Value) -> Option<Vec<u8>> {
        let end = at.checked_add(width.bytes())?;
        if end > self.source.len() {
            return None;
        }
        let mut bytes = self.source.to_vec();
        let field = &mut bytes[at..end];
        match value {
            Value::Int(value) => field.copy_from_slice(&value.to_le_bytes()[..width.bytes()]),
            Value::Float(value) => field.copy_from_slice(&value.to_le_bytes()),
        }
        Some(bytes)
    }

    fn field(&mut self, kind: Kind, name: &str, at: usize, width: Width, headline: &[u64]) {
        let Some(original) = read_int(self.source, at, width) else {
            return;
        };
        let len = self.source.len() as u64;
        let candidates = [
            0,
            1,
            width.max(),
            width.max() - 1,
            width.max() / 2 + 1,
            original.wrapping_add(1),
            original.wrapping_sub(1),
            original.wrapping_mul(2),
            len,
            len + 1,
        ];
        for value in candidates {
            let value = value & width.max();
            if let Some(bytes) = self.patched(at, width, Value::Int(value)) {
                let is_headline = headline.contains(&value);
                self.push(kind, format!("{name}={value}"), is_headline, bytes);
            }
        }
    }

    fn float_field(&mut self, name: &str, at: usize, headline: bool) {
        let values = [
            ("0", 0.0),
            ("nan", f64::NAN),
            ("inf", f64::INFINITY),
            ("-inf", f64::NEG_INFINITY),
            ("denormal", 1e-310),
            ("1e300", 1e300),
        ];
        for (label, value) in values {
            if let Some(bytes) = self.patched(at, Width::F64, Value::Float(value)) {
                let is_headline = match label {
                    "0" => headline && name.ends_with("scale"),
                    "nan" | "inf" => headline,
                    _ => false,
                };
                self.push(
                    Kind::HeaderField,
                    format!("{name}={label}"),
                    is_headline,
                    bytes,
                );
            }
        }
    }

    fn truncate(&mut self, len: usize, headline: bool) {
        if len < self.source.len() {
            let bytes = self.source[..len].to_vec();
            self.push(Kind::Truncate, format!("at-{len}"), headline, bytes);
        }
    }

    /// `count` files with 1 to 8 random bytes of `range` xored with a non-zero value.
    fn flips(&mut self, kind: Kind, range: std::ops::Range<usize>, count: usize, seed: u64) {
        if range.is_empty() {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for index in 0..count {
            let mut bytes = self.source.to_vec();
            let flips = 1 + index % 8;
            for _ in 0..flips {
                let at = rng.random_range(range.clone());
                bytes[at] ^= rng.random_range(1..=255u8);
            }
            self.push(kind, format!("{index}"), index == 0, bytes);
        }
    }
}

fn read_int(bytes: &[u8], at: usize, width: Width) -> Option<u64> {
    let field = bytes.get(at..at + width.bytes())?;
    let mut word = [0u8; 8];
    word[..field.len()].copy_from_slice(field);
    Some(u64::from_le_bytes(word))
}

/// Every mutant of `source`; `seed` fixes its byte flips.
pub fn mutants(source: &Source, seed: u64) -> Result<Vec<Mutant>, CorpusError> {
    let layout = Layout::of(&source.name, &source.bytes)?;
    let mut mutants = Mutants {
        source: &source.bytes,
        list: Vec::new(),
    };
    truncations(&mut mutants, &layout);
    header_fields(&mut mutants, &layout);
    for (index, vlr) in layout.vlrs.iter().enumerate() {
        vlr_fields(&mut mutants, index, vlr);
    }
    if let Some(first) = layout.first_evlr {
        evlr_fields(&mut mutants, first);
    }
    if let Some(laszip) = layout.laszip() {
        laszip_fields(&mut mutants, &laszip);
    }
    if let Some(table) = layout.chunk_table {
        chunk_table(&mut mutants, &layout, table, seed);
    }
    let vlr_end = layout
        .vlrs
        .last()
        .map_or(layout.header_size, |vlr| vlr.data_offset() + vlr.data_len);
    mutants.flips(Kind::FlipHeader, 0..layout.header_size, 12, seed ^ 1);
    mutants.flips(Kind::FlipVlrs, layout.header_size..vlr_end, 12, seed ^ 2);
    let points_end = layout.chunk_table.unwrap_or(source.bytes.len());
    mutants.flips(
        Kind::FlipPoints,
        layout.data_start..points_end,
        16,
        seed ^ 3,
    );
    Ok(mutants.list)
}

fn truncations(mutants: &mut Mutants<'_>, layout: &Layout) {
    let len = mutants.source.len();
    let data_start = layout.data_start;
    let mut cuts = vec![0, 1, 4, 24, 100, 226, 227, layout.header_size - 1];
    for vlr in &layout.vlrs {
        cuts.extend([vlr.offset + 1, vlr.data_offset() + vlr.data_len - 1]);
    }
    cuts.extend([data_start, data_start + 1, data_start + 8]);
    let points_end = layout.chunk_table.unwrap_or(len);
    let points = points_end.saturating_sub(data_start);
    cuts.extend([10, 25, 75, 90, 99].map(|percent| data_start + points * percent / 100));
    if let Some(table) = layout.chunk_table {
        cuts.extend([table, table + 4, table + 8]);
    }
    if let Some(first) = layout.first_evlr {
        cuts.extend([first, first + EVLR_HEADER_LEN / 2]);
    }
    cuts.extend([len.saturating_sub(8), len - 1]);
    for cut in cuts {
        mutants.truncate(cut, false);
    }
    mutants.truncate(data_start + points / 2, true);
}

fn header_fields(mutants: &mut Mutants<'_>, layout: &Layout) {
    use Width::*;
    let len = mutants.source.len() as u64;
    let count_extremes = [u64::from(u32::MAX), u64::MAX];
    let fields = [
        ("version-major", header::VERSION_MAJOR, U8, &[][..]),
        ("version-minor", header::VERSION_MINOR, U8, &[][..]),
        ("header-size", header::HEADER_SIZE, U16, &[0][..]),
        (
            "offset-to-points",
            header::OFFSET_TO_POINT_DATA,
            U32,
            &[len + 1][..],
        ),
        (
            "vlr-count",
            header::VLR_COUNT,
            U32,
            &[u64::from(u32::MAX)][..],
        ),
        ("point-format", header::POINT_FORMAT, U8, &[][..]),
        (
            "record-length",
            header::RECORD_LENGTH,
            U16,
            &[0, 65_535][..],
        ),
        (
            "legacy-point-count",
            header::LEGACY_POINT_COUNT,
            U32,
            &count_extremes[..],
        ),
    ];
    for (name, at, width, headline) in fields {
        mutants.field(Kind::HeaderField, name, at, width, headline);
    }
    // The compression bit alone, both ways.
    if let Some(bytes) = mutants.patched(
        header::POINT_FORMAT,
        U8,
        Value::Int(u64::from(mutants.source[header::POINT_FORMAT] ^ 0x80)),
    ) {
        mutants.push(Kind::HeaderField, "compression-bit".into(), true, bytes);
    }
    let transforms = [
        "x-scale", "y-scale", "z-scale", "x-offset", "y-offset", "z-offset",
    ];
    for (index, name) in transforms.iter().enumerate() {
        mutants.float_field(name, header::X_SCALE + 8 * index, index == 0 || index == 3);
    }
    mutants.float_field("max-x", header::BOUNDS, false);
    mutants.float_field("min-z", header::BOUNDS + 40, false);
    if layout.minor_version >= 3 {
        let at = header::WAVEFORM_START;
        mutants.field(Kind::HeaderField, "waveform-start", at, U64, &[]);
    }
    if layout.minor_version >= 4 {
        let evlr_extremes = [len + 1, u64::MAX];
        let at = header::FIRST_EVLR;
        mutants.field(Kind::HeaderField, "first-evlr", at, U64, &evlr_extremes);
        let at = header::EVLR_COUNT;
        mutants.field(
            Kind::HeaderField,
            "evlr-count",
            at,
            U32,
            &[u64::from(u32::MAX)],
        );
        let at = header::POINT_COUNT_1_4;
        mutants.field(Kind::HeaderField, "point-count", at, U64, &count_extremes);
    }
}

fn vlr_fields(mutants: &mut Mutants<'_>, index: usize, vlr: &Record) {
    let name = |field: &str| format!("vlr{index}-{field}");
    let at = vlr.offset;
    mutants.field(Kind::VlrField, &name("reserved"), at, Width::U16, &[]);
    mutants.field(Kind::VlrField, &name("record-id"), at + 18, Width::U16, &[]);
    // One VLR per source is enough for the fast subset.
    let headline: &[u64] = if index == 0 { &[0, 65_535] } else { &[] };
    mutants.field(
        Kind::VlrField,
        &name("length"),
        at + 20,
        Width::U16,
        headline,
    );
    let mut bytes = mutants.source.to_vec();
    bytes[at + 2..at + 18].fill(0);
    mutants.push(Kind::VlrField, name("user-id-cleared"), false, bytes);
}

fn evlr_fields(mutants: &mut Mutants<'_>, first: usize) {
    let lengths = [
        ("0", 0),
        ("1", 1),
        ("1gib", 1 << 30),
        ("8gib", 8 << 30),
        ("1tib", 1 << 40),
        ("max", u64::MAX),
    ];
    for (label, value) in lengths {
        if let Some(bytes) = mutants.patched(first + 20, Width::U64, Value::Int(value)) {
            let headline = matches!(label, "8gib" | "1tib");
            mutants.push(Kind::EvlrField, format!("length={label}"), headline, bytes);
        }
    }
    mutants.field(Kind::EvlrField, "record-id", first + 18, Width::U16, &[]);
}

fn laszip_fields(mutants: &mut Mutants<'_>, laszip: &Record) {
    use Width::*;
    let at = laszip.data_offset();
    let chunk_extremes = [0, u64::from(u32::MAX), u64::from(u32::MAX) - 1];
    let fields = [
        ("compressor", at, U16, &[0, 65_535][..]),
        ("coder", at + 2, U16, &[][..]),
        ("version-major", at + 4, U8, &[][..]),
        ("options", at + 8, U32, &[][..]),
        ("chunk-size", at + 12, U32, &chunk_extremes[..]),
        ("special-evlr-count", at + 16, U64, &[][..]),
        ("special-evlr-offset", at + 24, U64, &[][..]),
        ("item-count", at + 32, U16, &[0, 65_535][..]),
    ];
    for (name, offset, width, headline) in fields {
        mutants.field(Kind::LaszipField, name, offset, width, headline);
    }
    let items = read_int(mutants.source, at + 32, U16).unwrap_or(0) as usize;
    for item in 0..items {
        let item_at = at + 34 + 6 * item;
        let name = |field: &str| format!("item{item}-{field}");
        mutants.field(Kind::LaszipField, &name("type"), item_at, U16, &[]);
        mutants.field(Kind::LaszipField, &name("size"), item_at + 2, U16, &[0]);
        mutants.field(Kind::LaszipField, &name("version"), item_at + 4, U16, &[]);
    }
}

fn chunk_table(mutants: &mut Mutants<'_>, layout: &Layout, table: usize, seed: u64) {
    let offset_extremes = [0, u64::MAX, i64::MAX as u64];
    let at = layout.data_start;
    mutants.field(
        Kind::ChunkTable,
        "table-offset",
        at,
        Width::U64,
        &offset_extremes,
    );
    mutants.field(Kind::ChunkTable, "table-version", table, Width::U32, &[]);
    let count_extremes = [u64::from(u32::MAX), 0];
    mutants.field(
        Kind::ChunkTable,
        "chunk-count",
        table + 4,
        Width::U32,
        &count_extremes,
    );
    let entries_end = layout.first_evlr.unwrap_or(mutants.source.len());
    mutants.flips(Kind::ChunkTable, table + 8..entries_end, 8, seed ^ 4);
    // Entries of all ones decode to offsets the laz crate indexes with unchecked.
    if table + 8 < entries_end {
        let mut filled = mutants.source.to_vec();
        filled[table + 8..entries_end].fill(0xFF);
        mutants.push(
            Kind::ChunkTable,
            "entries-all-ones".to_owned(),
            true,
            filled,
        );
    }
}
