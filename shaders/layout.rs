//! The numbers both the host and the shaders rely on, stated once.
//!
//! Each is a Rust constant here, and [`wgsl_prelude`] declares it as a WGSL `const` of the
//! same name at the top of every composed module ([`crate::Shader::source`]); a test fails if
//! a WGSL file declares one of these names itself. They are WGSL `const`s rather than
//! pipeline-overridable constants because the shaders use them where only a `const` will do
//! or where a fixed value matters: as the length of a function-local array (the resolve
//! runs), as loop trip counts the compiler unrolls, in the `const` expressions that derive
//! masks and steps from them (the position bits), and as workgroup sizes; and none of them
//! varies from pipeline to pipeline. What the host picks per pipeline (the point size, the
//! point passes' workgroup size, whether a resolve writes depth) stays an `override` that the
//! pipeline sets.

/// Points per batch: one workgroup culls and rasterizes one batch; the benchmark's
/// `PointList` baseline finds a point's batch as `index / BATCH_POINTS`.
pub const BATCH_POINTS: u32 = 4096;

/// Points per sub-batch: the host keeps the box of every run of this many points of a batch
/// and lists only the runs in view of a batch that straddles the view's edge; a listed entry
/// names its runs in units of this many points (`listed_batch` in common.wgsl).
pub const SUB_BATCH_POINTS: u32 = 256;
const _: () = assert!(BATCH_POINTS.is_multiple_of(SUB_BATCH_POINTS));

/// Bits of a quantised position per axis (x, y, z), in two u32 words: x in bits 0..21 of the
/// first, y in bits 21..32 of the first and 0..10 of the second, z in bits 10..32 of the
/// second, each a fraction of the batch's box in steps of `extent / (2^bits - 1)`.
pub const POSITION_BITS: [u32; 3] = [21, 21, 22];
const _: () = assert!(POSITION_BITS[0] + POSITION_BITS[1] + POSITION_BITS[2] == 64);
const _: () = assert!(POSITION_BITS[0] < 32 && POSITION_BITS[0] + POSITION_BITS[1] > 32);

/// The reciprocal of the largest quantised value of each axis, `1 / (2^bits - 1)` rounded to
/// f32 once: host and shaders multiply a batch's extent by it to get the quantisation step,
/// so both dequantise to the same f32 positions.
pub const INV_QUANT_MAX: [f32; 3] = [
    1.0 / ((1u32 << POSITION_BITS[0]) - 1) as f32,
    1.0 / ((1u32 << POSITION_BITS[1]) - 1) as f32,
    1.0 / ((1u32 << POSITION_BITS[2]) - 1) as f32,
];

/// Side in pixels of the square occlusion tiles that hold the largest depth of their pixels
/// (occlusion.wgsl, occlusion_tiles.wgsl).
pub const OCCLUSION_TILE: u32 = 16;

/// Invocations per workgroup of `clear_tiles`, one tile each (occlusion_tiles.wgsl).
pub const OCCLUSION_CLEAR_WORKGROUP: u32 = 64;

/// Side of the square workgroup of `build_tiles`, one tile an invocation
/// (occlusion_tiles.wgsl).
pub const OCCLUSION_BUILD_WORKGROUP_SIDE: u32 = 8;

/// Consecutive pixels per invocation of `resolve` (resolve.wgsl says why runs;
/// docs/perf/resolve-runs.md has the lengths' figures).
pub const RESOLVE_RUN: u32 = 8;

/// Consecutive pixels per invocation of the high-quality `resolve_average`s: four words a
/// pixel, and shorter runs than [`RESOLVE_RUN`] were faster (docs/perf/resolve-runs.md).
pub const AVERAGE_RUN: u32 = 4;

/// Invocations per workgroup of the framebuffer's clear and resolves (resolve.wgsl).
pub const RESOLVE_WORKGROUP: u32 = 256;

/// Side of the square workgroup of the passes over the resolved image (edl.wgsl,
/// visibility.wgsl's `classify`, pintus.wgsl): one invocation a pixel.
pub const SCREEN_TILE: u32 = 16;

/// Invocations per workgroup of the filling's passes over the list of mutable pixels
/// (fill.wgsl), whose indirect dispatch visibility.wgsl prepares.
pub const LIST_WORKGROUP: u32 = 64;

/// The `u32` constants of the prelude, by their name in WGSL (and here).
pub const U32_CONSTANTS: [(&str, u32); 10] = [
    ("BATCH_POINTS", BATCH_POINTS),
    ("SUB_BATCH_POINTS", SUB_BATCH_POINTS),
    ("OCCLUSION_TILE", OCCLUSION_TILE),
    ("OCCLUSION_CLEAR_WORKGROUP", OCCLUSION_CLEAR_WORKGROUP),
    (
        "OCCLUSION_BUILD_WORKGROUP_SIDE",
        OCCLUSION_BUILD_WORKGROUP_SIDE,
    ),
    ("RESOLVE_RUN", RESOLVE_RUN),
    ("AVERAGE_RUN", AVERAGE_RUN),
    ("RESOLVE_WORKGROUP", RESOLVE_WORKGROUP),
    ("SCREEN_TILE", SCREEN_TILE),
    ("LIST_WORKGROUP", LIST_WORKGROUP),
];

/// Names of every constant the prelude declares.
pub fn names() -> impl Iterator<Item = &'static str> {
    U32_CONSTANTS
        .iter()
        .map(|&(name, _)| name)
        .chain(["POSITION_BITS", "INV_QUANT_MAX"])
}

/// The WGSL declarations of this module's constants, one `const` each.
pub fn wgsl_prelude() -> String {
    let mut prelude =
        String::from("// Constants shared with the host (pointfarm_shaders::layout).\n");
    for (name, value) in U32_CONSTANTS {
        prelude.push_str(&format!("const {name}: u32 = {value}u;\n"));
    }
    let [x, y, z] = POSITION_BITS;
    prelude.push_str(&format!(
        "const POSITION_BITS: vec3<u32> = vec3<u32>({x}u, {y}u, {z}u);\n"
    ));
    let [x, y, z] = INV_QUANT_MAX.map(wgsl_f32);
    prelude.push_str(&format!(
        "const INV_QUANT_MAX: vec3<f32> = vec3<f32>({x}, {y}, {z});\n"
    ));
    prelude
}

/// `value` as a WGSL f32 literal of exactly its bits: a hexadecimal float, so no decimal
/// rounding can move it by an ulp.
fn wgsl_f32(value: f32) -> String {
    assert!(value.is_normal(), "{value} is not a normal f32");
    let bits = value.to_bits();
    let sign = if bits >> 31 == 1 { "-" } else { "" };
    let exponent = ((bits >> 23) & 0xff) as i32 - 127;
    // 23 fraction bits, shifted to fill six hexadecimal digits.
    let fraction = (bits & 0x7f_ffff) << 1;
    format!("{sign}0x1.{fraction:06x}p{exponent}f")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hexadecimal_literals_hold_the_exact_bits() {
        assert_eq!(wgsl_f32(1.0), "0x1.000000p0f");
        assert_eq!(wgsl_f32(-0.375), "-0x1.800000p-2f");
        assert_eq!(wgsl_f32(INV_QUANT_MAX[0]), "0x1.000008p-21f");
        assert_eq!(wgsl_f32(INV_QUANT_MAX[2]), "0x1.000004p-22f");
    }

    #[test]
    fn the_prelude_declares_every_name_once() {
        let prelude = wgsl_prelude();
        for name in names() {
            let declaration = format!("const {name}: ");
            assert_eq!(prelude.matches(&declaration).count(), 1, "{name}");
        }
    }
}
