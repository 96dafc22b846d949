//! `DatasetStats`: what color decisions need about the whole dataset, gathered in the
//! counting pass so colors can be decided once, not per node.

/// Bins of the intensity histogram: one per 16-bit value, so percentiles are exact.
pub const INTENSITY_BINS: usize = 1 << 16;

#[derive(Debug, Clone, PartialEq)]
pub struct DatasetStats {
    /// Whether the source's points carry raw RGB.
    pub has_rgb: bool,
    /// The largest raw value of each RGB channel (all 255 or less: 8-bit values in 16-bit
    /// fields).
    pub max_rgb: [u16; 3],
    /// The smallest raw value of each RGB channel: equal to `max_rgb` when every point has one
    /// color.
    pub min_rgb: [u16; 3],
    /// Points per intensity value.
    pub intensity_histogram: Vec<u64>,
    /// Points per classification code.
    pub class_counts: Vec<u64>,
    /// Lowest and highest z of the points.
    pub z_range: [f64; 2],
}

impl DatasetStats {
    pub fn new(has_rgb: bool) -> Self {
        Self {
            has_rgb,
            max_rgb: [0; 3],
            min_rgb: [u16::MAX; 3],
            intensity_histogram: vec![0; INTENSITY_BINS],
            class_counts: vec![0; 256],
            z_range: [f64::INFINITY, f64::NEG_INFINITY],
        }
    }

    /// Bytes this holds in memory.
    pub(crate) const HEAP_BYTES: u64 = (INTENSITY_BINS as u64 + 256) * 8;

    /// The largest raw value of any RGB channel.
    pub fn max_rgb_channel(&self) -> u16 {
        self.max_rgb.into_iter().max().unwrap_or(0)
    }

    /// Adds a decoded node's points (statistics of a sample of nodes, where the points were
    /// never streamed whole: a COPC file's coarsest nodes).
    pub fn add_node(&mut self, node: &super::codec::NodePoints) {
        if let Some(rgb) = &node.rgb {
            for c in rgb {
                for ((max, min), &value) in self.max_rgb.iter_mut().zip(&mut self.min_rgb).zip(c) {
                    *max = (*max).max(value);
                    *min = (*min).min(value);
                }
            }
        }
        for &i in &node.intensity {
            self.intensity_histogram[usize::from(i)] += 1;
        }
        for &c in &node.classification {
            self.class_counts[usize::from(c)] += 1;
        }
        for p in node.world_positions() {
            self.z_range[0] = self.z_range[0].min(p.z);
            self.z_range[1] = self.z_range[1].max(p.z);
        }
    }

    /// Adds the intensities and classes of the points `range` of `batch`; their RGB and z
    /// come through [`Self::add_facts`].
    pub(crate) fn add_counts(
        &mut self,
        batch: &super::source::PointBatch<'_>,
        range: std::ops::Range<usize>,
    ) {
        for &i in &batch.intensity[range.clone()] {
            self.intensity_histogram[usize::from(i)] += 1;
        }
        for &c in &batch.classification[range] {
            self.class_counts[usize::from(c)] += 1;
        }
    }

    /// Adds the RGB range (where the source has RGB) and z range of points whose facts the
    /// counting pass gathered as it made their records.
    pub(crate) fn add_facts(&mut self, facts: &super::file_facts::FileFacts) {
        if self.has_rgb {
            for c in 0..3 {
                self.max_rgb[c] = self.max_rgb[c].max(facts.max_rgb[c]);
                self.min_rgb[c] = self.min_rgb[c].min(facts.min_rgb[c]);
            }
        }
        self.z_range[0] = self.z_range[0].min(facts.min.z);
        self.z_range[1] = self.z_range[1].max(facts.max.z);
    }

    pub(crate) fn add(&mut self, batch: &super::source::PointBatch<'_>) {
        self.add_range(batch, 0..batch.len());
    }

    /// Adds the points `range` of `batch`.
    pub(crate) fn add_range(
        &mut self,
        batch: &super::source::PointBatch<'_>,
        range: std::ops::Range<usize>,
    ) {
        if let Some(rgb) = batch.rgb {
            for c in &rgb[range.clone()] {
                for ((max, min), &value) in self.max_rgb.iter_mut().zip(&mut self.min_rgb).zip(c) {
                    *max = (*max).max(value);
                    *min = (*min).min(value);
                }
            }
        }
        for &i in &batch.intensity[range.clone()] {
            self.intensity_histogram[usize::from(i)] += 1;
        }
        for &c in &batch.classification[range.clone()] {
            self.class_counts[usize::from(c)] += 1;
        }
        for p in &batch.positions[range] {
            self.z_range[0] = self.z_range[0].min(p.z);
            self.z_range[1] = self.z_range[1].max(p.z);
        }
    }
}
