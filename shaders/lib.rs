//! The WGSL sources of the renderer, embedded at build time.
//!
//! WGSL has no `#include`, so every module is composed as the [`layout`] prelude (the
//! constants host and shaders share), `common.wgsl`, the files it shares with passes of its
//! kind ([`Shader::source`]), then its own file (the resolve's followed by the file that
//! says where it finds the high-quality sums). The renderer only ever asks for a
//! [`Shader`]; the tests below validate every composed module with naga, the ones that must
//! run without 64-bit integers also with capabilities that lack them, so a broken shader fails
//! CI even when no test renders it.

pub mod layout;

/// One shader module of the renderer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Shader {
    /// Basic mode with 64-bit atomics: one pass, entry point `rasterize`.
    RasterAtomic64,
    /// Basic mode with 32-bit atomics: entry points `rasterize_depth`, `rasterize_color`.
    RasterAtomic32,
    /// High-quality mode's color accumulation with 32-bit atomics: entry point `accumulate`.
    HqAccumulate,
    /// The same with 64-bit atomicAdd (`SHADER_INT64_ATOMIC_ALL_OPS`), two atomics a point.
    HqAccumulate64,
    /// High-quality accumulation of a level-of-detail cut's pages, each point weighted by the
    /// original points it stands for, with 32-bit atomics: entry point `accumulate`.
    HqAccumulateWeighted,
    /// The same with 64-bit atomicAdd.
    HqAccumulateWeighted64,
    /// Eye-Dome Lighting on the resolved images: entry point `shade`.
    Edl,
    /// Framebuffer clear and resolve: entry points `clear`, `resolve`, and `resolve_average`
    /// after the 32-bit high-quality accumulation.
    Resolve,
    /// The same, its `resolve_average` after the 64-bit accumulation (the packed sums).
    ResolvePacked,
    /// Pintus et al.'s screen-space visibility on the resolved images: entry point `classify`.
    Visibility,
    /// Pintus et al.'s anisotropic filling: entry points `fill_step`, `finish`.
    Fill,
    /// Pintus et al.'s multi-level shape-depicting shading: entry points `level`, `apply`.
    PintusShading,
    /// The benchmark's fixed-function baseline, a `PointList` render pipeline: entry points
    /// `vertex_main`, `fragment_main`. Only with the `pointlist-baseline` feature.
    #[cfg(feature = "pointlist-baseline")]
    PointListBaseline,
    /// The occlusion tiles between point dispatches: entry points `clear_tiles`,
    /// `build_tiles`.
    OcclusionTiles,
}

const COMMON: &str = include_str!("common.wgsl");
/// The occlusion test of whole batches, after `common.wgsl` in the point passes.
const OCCLUSION: &str = include_str!("occlusion.wgsl");
/// The point passes' bindings and batch, after the occlusion test.
const POINT_PASS: &str = include_str!("point_pass.wgsl");
/// The high-quality accumulation, after its per-pixel sums (one of the two below).
const HQ_ACCUMULATE: &str = include_str!("hq_accumulate.wgsl");
/// The weighted high-quality accumulation of a cut's pages, after its per-pixel sums.
const HQ_ACCUMULATE_WEIGHTED: &str = include_str!("hq_accumulate_weighted.wgsl");
/// What both high-quality accumulations share, between their sums and their own file: the
/// framebuffer, the entry point and the depth band's test.
const HQ_BAND: &str = include_str!("hq_band.wgsl");
const HQ_SUMS_ATOMIC32: &str = include_str!("hq_sums_atomic32.wgsl");
const HQ_SUMS_ATOMIC64: &str = include_str!("hq_sums_atomic64.wgsl");
/// Parameters and helpers of the passes on the resolved images, after `common.wgsl`.
const SCREEN_COMMON: &str = include_str!("screen_common.wgsl");
/// Where the high-quality resolve finds the sums, after `resolve.wgsl`: the 32-bit
/// accumulation's, or the 64-bit one's packed sums.
const RESOLVE_SUMS: &str = include_str!("resolve_sums.wgsl");
const RESOLVE_SUMS_PACKED: &str = include_str!("resolve_sums_packed.wgsl");

impl Shader {
    pub const ALL: &'static [Shader] = &[
        Shader::RasterAtomic64,
        Shader::RasterAtomic32,
        Shader::HqAccumulate,
        Shader::HqAccumulate64,
        Shader::HqAccumulateWeighted,
        Shader::HqAccumulateWeighted64,
        Shader::Edl,
        Shader::Resolve,
        Shader::ResolvePacked,
        Shader::Visibility,
        Shader::Fill,
        Shader::PintusShading,
        #[cfg(feature = "pointlist-baseline")]
        Shader::PointListBaseline,
        Shader::OcclusionTiles,
    ];

    /// A label for debuggers and logs.
    pub fn label(self) -> &'static str {
        match self {
            Shader::RasterAtomic64 => "raster_atomic64",
            Shader::RasterAtomic32 => "raster_atomic32",
            Shader::HqAccumulate => "hq_accumulate",
            Shader::HqAccumulate64 => "hq_accumulate64",
            Shader::HqAccumulateWeighted => "hq_accumulate_weighted",
            Shader::HqAccumulateWeighted64 => "hq_accumulate_weighted64",
            Shader::Edl => "edl",
            Shader::Resolve => "resolve",
            Shader::ResolvePacked => "resolve_packed",
            Shader::Visibility => "visibility",
            Shader::Fill => "fill",
            Shader::PintusShading => "pintus",
            #[cfg(feature = "pointlist-baseline")]
            Shader::PointListBaseline => "pointlist_baseline",
            Shader::OcclusionTiles => "occlusion_tiles",
        }
    }

    /// The complete WGSL source of the module.
    pub fn source(self) -> String {
        let own = match self {
            Shader::RasterAtomic64 => include_str!("raster_atomic64.wgsl"),
            Shader::RasterAtomic32 => include_str!("raster_atomic32.wgsl"),
            Shader::HqAccumulate | Shader::HqAccumulate64 => HQ_ACCUMULATE,
            Shader::HqAccumulateWeighted | Shader::HqAccumulateWeighted64 => HQ_ACCUMULATE_WEIGHTED,
            Shader::Edl => include_str!("edl.wgsl"),
            Shader::Resolve | Shader::ResolvePacked => include_str!("resolve.wgsl"),
            Shader::Visibility => include_str!("visibility.wgsl"),
            Shader::Fill => include_str!("fill.wgsl"),
            Shader::PintusShading => include_str!("pintus.wgsl"),
            #[cfg(feature = "pointlist-baseline")]
            Shader::PointListBaseline => include_str!("pointlist_baseline.wgsl"),
            Shader::OcclusionTiles => include_str!("occlusion_tiles.wgsl"),
        };
        let prelude = layout::wgsl_prelude();
        let composed = match self {
            Shader::Visibility | Shader::Fill | Shader::PintusShading => {
                format!("{COMMON}\n{SCREEN_COMMON}\n{own}")
            }
            Shader::RasterAtomic64 | Shader::RasterAtomic32 => {
                format!("{COMMON}\n{OCCLUSION}\n{POINT_PASS}\n{own}")
            }
            Shader::HqAccumulate | Shader::HqAccumulateWeighted => {
                format!("{COMMON}\n{OCCLUSION}\n{POINT_PASS}\n{HQ_SUMS_ATOMIC32}\n{HQ_BAND}\n{own}")
            }
            Shader::HqAccumulate64 | Shader::HqAccumulateWeighted64 => {
                format!("{COMMON}\n{OCCLUSION}\n{POINT_PASS}\n{HQ_SUMS_ATOMIC64}\n{HQ_BAND}\n{own}")
            }
            Shader::Resolve => format!("{COMMON}\n{own}\n{RESOLVE_SUMS}"),
            Shader::ResolvePacked => format!("{COMMON}\n{own}\n{RESOLVE_SUMS_PACKED}"),
            _ => format!("{COMMON}\n{own}"),
        };
        format!("{prelude}\n{composed}")
    }
}

#[cfg(test)]
mod tests {
    use super::{layout, Shader};
    use naga::valid::{Capabilities, ValidationFlags, Validator};

    /// Capabilities of a device without 64-bit integers: everything else naga knows.
    fn without_int64() -> Capabilities {
        Capabilities::all()
            - Capabilities::SHADER_INT64
            - Capabilities::SHADER_INT64_ATOMIC_MIN_MAX
            - Capabilities::SHADER_INT64_ATOMIC_ALL_OPS
            - Capabilities::TEXTURE_INT64_ATOMIC
    }

    /// The shaders that need 64-bit integer atomics; every other one must run without them.
    fn needs_int64(shader: Shader) -> bool {
        matches!(
            shader,
            Shader::RasterAtomic64 | Shader::HqAccumulate64 | Shader::HqAccumulateWeighted64
        )
    }

    fn parse(shader: Shader) -> naga::Module {
        naga::front::wgsl::parse_str(&shader.source()).unwrap_or_else(|e| {
            panic!("{}: {}", shader.label(), e.emit_to_string(&shader.source()))
        })
    }

    fn validate(shader: Shader, capabilities: Capabilities) -> Result<(), String> {
        Validator::new(ValidationFlags::all(), capabilities)
            .validate(&parse(shader))
            .map(drop)
            .map_err(|e| e.emit_to_string(&shader.source()))
    }

    #[test]
    fn every_shader_parses_and_validates() {
        for &shader in Shader::ALL {
            if let Err(e) = validate(shader, Capabilities::all()) {
                panic!("{}: {e}", shader.label());
            }
        }
    }

    #[test]
    fn the_32_bit_shaders_validate_without_64_bit_integers() {
        for shader in Shader::ALL.iter().copied().filter(|&s| !needs_int64(s)) {
            if let Err(e) = validate(shader, without_int64()) {
                panic!("{} uses 64-bit integers: {e}", shader.label());
            }
        }
    }

    /// The check above would catch a 64-bit type: the 64-bit shaders fail it.
    #[test]
    fn the_64_bit_shaders_need_64_bit_integers() {
        for shader in Shader::ALL.iter().copied().filter(|&s| needs_int64(s)) {
            assert!(
                validate(shader, without_int64()).is_err(),
                "{} validates without 64-bit integers",
                shader.label()
            );
        }
    }

    /// Only the prelude declares the shared constants: a WGSL file that stated one of them
    /// again (as a `const` or an `override`) would let it drift from the host's.
    #[test]
    fn no_wgsl_file_redeclares_a_shared_constant() {
        for shader in Shader::ALL {
            let source = shader.source();
            for name in layout::names() {
                for keyword in ["const", "override", "let", "var"] {
                    let declared = source
                        .match_indices(&format!("{keyword} {name}"))
                        .filter(|&(at, found)| {
                            let after = source[at + found.len()..].chars().next();
                            !after.is_some_and(|c| c.is_alphanumeric() || c == '_')
                        })
                        .count();
                    let expected = usize::from(keyword == "const");
                    assert_eq!(
                        declared,
                        expected,
                        "{}: `{keyword} {name}` {declared} times; only the layout prelude may \
                         declare it",
                        shader.label()
                    );
                }
            }
        }
    }

    /// The shaders' quantisation steps are the host's to the bit: the prelude's
    /// `INV_QUANT_MAX` parses back to [`layout::INV_QUANT_MAX`].
    #[test]
    fn the_shaders_inverse_quantisation_maxima_are_the_hosts() {
        let module = parse(Shader::RasterAtomic32);
        let (_, constant) = module
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some("INV_QUANT_MAX"))
            .expect("INV_QUANT_MAX is declared");
        let naga::Expression::Compose { components, .. } =
            &module.global_expressions[constant.init]
        else {
            panic!("INV_QUANT_MAX is not a vector constructor");
        };
        let values: Vec<u32> = components
            .iter()
            .map(|&c| match module.global_expressions[c] {
                naga::Expression::Literal(naga::Literal::F32(v)) => v.to_bits(),
                ref other => panic!("INV_QUANT_MAX holds {other:?}"),
            })
            .collect();
        assert_eq!(values, layout::INV_QUANT_MAX.map(f32::to_bits));
    }
}
