//! The WGSL sources of the renderer, embedded at build time.
//!
//! WGSL has no `#include`, so every point pass is composed as `common.wgsl` followed by the
//! pass's own file. The renderer only ever asks for a [`Shader`]; the tests below validate
//! every composed module with naga, so a broken shader fails CI even when no test renders it.

/// One shader module of the renderer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Shader {
    /// Basic mode with 64-bit atomics: one pass, entry point `rasterize`.
    RasterAtomic64,
    /// Basic mode with 32-bit atomics: entry points `rasterize_depth`, `rasterize_color`.
    RasterAtomic32,
    /// High-quality mode's colour accumulation with 32-bit atomics: entry point `accumulate`.
    HqAccumulate,
    /// The same with 64-bit atomicAdd (`SHADER_INT64_ATOMIC_ALL_OPS`), two atomics a point.
    HqAccumulate64,
    /// Eye-Dome Lighting on the resolved images: entry point `shade`.
    Edl,
    /// Framebuffer clear and resolve: entry points `clear`, `resolve`, `resolve_average`.
    Resolve,
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
/// The high-quality accumulation, after its per-pixel sums (one of the two below).
const HQ_ACCUMULATE: &str = include_str!("hq_accumulate.wgsl");
const HQ_SUMS_ATOMIC32: &str = include_str!("hq_sums_atomic32.wgsl");
const HQ_SUMS_ATOMIC64: &str = include_str!("hq_sums_atomic64.wgsl");
/// Parameters and helpers of the passes on the resolved images, after `common.wgsl`.
const SCREEN_COMMON: &str = include_str!("screen_common.wgsl");

impl Shader {
    pub const ALL: &'static [Shader] = &[
        Shader::RasterAtomic64,
        Shader::RasterAtomic32,
        Shader::HqAccumulate,
        Shader::HqAccumulate64,
        Shader::Edl,
        Shader::Resolve,
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
            Shader::Edl => "edl",
            Shader::Resolve => "resolve",
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
            Shader::Edl => include_str!("edl.wgsl"),
            Shader::Resolve => include_str!("resolve.wgsl"),
            Shader::Visibility => include_str!("visibility.wgsl"),
            Shader::Fill => include_str!("fill.wgsl"),
            Shader::PintusShading => include_str!("pintus.wgsl"),
            #[cfg(feature = "pointlist-baseline")]
            Shader::PointListBaseline => include_str!("pointlist_baseline.wgsl"),
            Shader::OcclusionTiles => include_str!("occlusion_tiles.wgsl"),
        };
        match self {
            Shader::Visibility | Shader::Fill | Shader::PintusShading => {
                format!("{COMMON}\n{SCREEN_COMMON}\n{own}")
            }
            Shader::RasterAtomic64 | Shader::RasterAtomic32 => {
                format!("{COMMON}\n{OCCLUSION}\n{own}")
            }
            Shader::HqAccumulate => format!("{COMMON}\n{OCCLUSION}\n{HQ_SUMS_ATOMIC32}\n{own}"),
            Shader::HqAccumulate64 => format!("{COMMON}\n{OCCLUSION}\n{HQ_SUMS_ATOMIC64}\n{own}"),
            _ => format!("{COMMON}\n{own}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Shader;

    #[test]
    fn every_shader_parses_and_validates() {
        for shader in Shader::ALL {
            let module = naga::front::wgsl::parse_str(&shader.source()).unwrap_or_else(|e| {
                panic!("{}: {}", shader.label(), e.emit_to_string(&shader.source()))
            });
            let mut validator = naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                naga::valid::Capabilities::all(),
            );
            if let Err(e) = validator.validate(&module) {
                panic!("{}: {}", shader.label(), e.emit_to_string(&shader.source()));
            }
        }
    }
}
