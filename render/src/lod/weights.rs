//! Point weights: how many original points a stored point stands for in high quality's
//! average where its node is drawn without the child below it (`sampling.rs` computes them).
//!
//! A weight is stored in 13 bits, a small float: 4 bits of exponent and 9 of mantissa, exact
//! to 1023 and within 1/1024 of the weight above (up to about 16.7 million), so that with the
//! point's octant (3 bits) it fits the 16 bits a node-cache page holds per point
//! (`shaders/hq_accumulate_weighted.wgsl` decodes it the same way). An 8-bit log code would
//! err by percents on every coarse point; 1/1024 moves an average of 8-bit colors by far less
//! than one level.

/// The extra bytes attribute (an unsigned 32-bit integer) in which a COPC export keeps each
/// point's weight, and from which a COPC file's points take theirs: a foreign file has none,
/// and its points count once.
pub const WEIGHT_ATTRIBUTE: &str = "pointfarm_weight";

/// Bits of a weight's code.
pub const WEIGHT_CODE_BITS: u32 = 13;
const MANTISSA_BITS: u32 = 9;
const MANTISSA: u32 = 1 << MANTISSA_BITS;
/// The largest weight a code holds; heavier ones saturate to it.
pub const MAX_WEIGHT: u32 = (2 * MANTISSA - 1) << 14;

/// The code of `weight` (0 stays 0), rounded to the nearest weight a code holds.
pub fn encode_weight(weight: u32) -> u16 {
    let weight = weight.min(MAX_WEIGHT);
    if weight < 2 * MANTISSA {
        return if weight < MANTISSA {
            weight as u16
        } else {
            (1 << MANTISSA_BITS | (weight - MANTISSA)) as u16
        };
    }
    // weight = (MANTISSA + m) << (e - 1) with e >= 2.
    let shift = 31 - weight.leading_zeros() - MANTISSA_BITS;
    let mut scaled = (weight + (1 << (shift - 1))) >> shift;
    let mut e = shift + 1;
    if scaled >= 2 * MANTISSA {
        scaled >>= 1;
        e += 1;
    }
    if e >= 1 << (WEIGHT_CODE_BITS - MANTISSA_BITS) {
        return ((1 << WEIGHT_CODE_BITS) - 1) as u16;
    }
    ((e << MANTISSA_BITS) | (scaled - MANTISSA)) as u16
}

/// The weight a code holds (its top 3 bits, where a page keeps the octant, ignored).
pub fn decode_weight(code: u16) -> u32 {
    let code = u32::from(code) & ((1 << WEIGHT_CODE_BITS) - 1);
    let (e, m) = (code >> MANTISSA_BITS, code & (MANTISSA - 1));
    if e == 0 {
        m
    } else {
        (MANTISSA + m) << (e - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_exact_to_1023_and_within_1_in_1024_above() {
        for w in 0..=1023 {
            assert_eq!(decode_weight(encode_weight(w)), w);
        }
        let mut w = 1024u32;
        while w < MAX_WEIGHT {
            let back = decode_weight(encode_weight(w));
            let error = (f64::from(back) - f64::from(w)).abs() / f64::from(w);
            assert!(error <= 1.0 / 1024.0, "{w} -> {back}");
            w = w + w / 7 + 1;
        }
        assert_eq!(decode_weight(encode_weight(u32::MAX)), MAX_WEIGHT);
        assert_eq!(encode_weight(MAX_WEIGHT), (1 << WEIGHT_CODE_BITS) - 1);
        // Every code decodes to a weight that encodes back to it.
        for code in 0..1u16 << WEIGHT_CODE_BITS {
            assert_eq!(encode_weight(decode_weight(code)), code);
        }
    }
}
