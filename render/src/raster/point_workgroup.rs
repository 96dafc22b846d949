//! How many invocations a point-pass workgroup has, chosen per adapter.
//!
//! A point pass runs one workgroup per batch, and each invocation walks the batch with a
//! stride of the workgroup size. A GPU wants a workgroup of several waves: 128 suits 32-wide
//! (NVIDIA, RDNA) and 64-wide (GCN) ones. A software rasterizer such as lavapipe runs the
//! invocations of a workgroup as SIMD vectors of one subgroup each, one vector after the
//! other. With a workgroup of one subgroup, that vector walks its Morton-ordered batch in order
//! instead of striding through it 128 points at a time, so consecutive iterations read
//! adjacent positions and write nearby pixels, which makes lavapipe's point pass faster
//! (docs/perf/point-workgroup-size.md).

use super::points::BATCH_POINTS;

/// Environment variable that overrides the point passes' workgroup size (for tuning runs).
pub const WORKGROUP_SIZE_ENV: &str = "POINTFARM_POINT_WORKGROUP";

/// The workgroup size on GPUs.
const GPU_WORKGROUP_SIZE: u32 = 128;

/// Threads per workgroup of the point passes on `adapter`, whose device allows `limit`
/// invocations per workgroup: `POINTFARM_POINT_WORKGROUP` when it is set and valid, else
/// [`default_size`].
pub(crate) fn point_workgroup_size(adapter: &wgpu::AdapterInfo, limit: u32) -> u32 {
    let default = default_size(adapter.device_type, adapter.subgroup_max_size, limit);
    let Ok(requested) = std::env::var(WORKGROUP_SIZE_ENV) else {
        return default;
    };
    match requested.trim().parse::<u32>() {
        Ok(n) if is_valid(n, limit) => n,
        _ => {
            tracing::warn!(
                value = requested,
                default,
                "ignoring {WORKGROUP_SIZE_ENV}: not a power of two up to {}",
                limit.min(1024)
            );
            default
        }
    }
}

/// One subgroup on a CPU adapter, [`GPU_WORKGROUP_SIZE`] elsewhere (see the module comment).
fn default_size(device_type: wgpu::DeviceType, subgroup_size: u32, limit: u32) -> u32 {
    if device_type == wgpu::DeviceType::Cpu && is_valid(subgroup_size, limit) {
        subgroup_size
    } else {
        GPU_WORKGROUP_SIZE.min(limit)
    }
}

/// A power of two within the device's limit; it then divides [`BATCH_POINTS`], so every
/// invocation of a full batch handles the same number of points.
fn is_valid(n: u32, limit: u32) -> bool {
    n.is_power_of_two() && n <= limit.min(1024)
}
const _: () = assert!(BATCH_POINTS.is_power_of_two() && BATCH_POINTS >= 1024);

#[cfg(test)]
mod tests {
    use super::*;
    use wgpu::DeviceType;

    #[test]
    fn software_adapters_get_one_subgroup_and_gpus_several_waves() {
        // lavapipe with 256-bit and with 128-bit vectors.
        assert_eq!(default_size(DeviceType::Cpu, 8, 1024), 8);
        assert_eq!(default_size(DeviceType::Cpu, 4, 1024), 4);
        for gpu in [DeviceType::DiscreteGpu, DeviceType::IntegratedGpu] {
            for subgroup in [32, 64] {
                assert_eq!(default_size(gpu, subgroup, 1024), 128);
            }
        }
    }

    #[test]
    fn odd_subgroup_sizes_and_small_limits_fall_back_safely() {
        assert_eq!(default_size(DeviceType::Cpu, 0, 1024), 128);
        assert_eq!(default_size(DeviceType::Cpu, 12, 1024), 128);
        assert_eq!(default_size(DeviceType::Cpu, 8, 4), 4);
        assert_eq!(default_size(DeviceType::DiscreteGpu, 32, 64), 64);
    }
}
