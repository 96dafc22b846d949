//! The one owner of the wgpu instance, adapter, device and queue.
//!
//! It prefers a hardware adapter and falls back to a software one (Mesa's lavapipe), and
//! records what the renderer may use: 64-bit atomics, timestamp queries and the storage
//! binding limit that decides how points are split into segments.

use std::fmt;
use std::str::FromStr;

use thiserror::Error;

/// Environment variable that forces the adapter choice: `auto`, `hardware` or `software`.
pub const ADAPTER_ENV: &str = "POINTFARM_ADAPTER";

/// Which kind of adapter to use.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AdapterChoice {
    /// A hardware GPU when there is one, else a software rasterizer.
    #[default]
    Auto,
    /// Only a hardware GPU.
    Hardware,
    /// Only a software rasterizer (lavapipe).
    Software,
}

impl FromStr for AdapterChoice {
    type Err = GpuError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" | "" => Ok(AdapterChoice::Auto),
            "hardware" | "gpu" => Ok(AdapterChoice::Hardware),
            "software" | "cpu" | "lavapipe" => Ok(AdapterChoice::Software),
            other => Err(GpuError::UnknownChoice(other.to_string())),
        }
    }
}

impl fmt::Display for AdapterChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            AdapterChoice::Auto => "auto",
            AdapterChoice::Hardware => "hardware",
            AdapterChoice::Software => "software",
        })
    }
}

impl AdapterChoice {
    /// The choice named by [`ADAPTER_ENV`], or `Auto` when it is unset.
    pub fn from_env() -> Result<Self, GpuError> {
        match std::env::var(ADAPTER_ENV) {
            Ok(value) => value.parse(),
            Err(_) => Ok(AdapterChoice::Auto),
        }
    }

    fn accepts(self, device_type: wgpu::DeviceType) -> bool {
        let software = device_type == wgpu::DeviceType::Cpu;
        match self {
            AdapterChoice::Auto => true,
            AdapterChoice::Hardware => !software,
            AdapterChoice::Software => software,
        }
    }
}

#[derive(Debug, Error)]
pub enum GpuError {
    #[error("unknown adapter choice '{0}' (expected auto, hardware or software)")]
    UnknownChoice(String),
    #[error(
        "no {choice} graphics adapter found (install Mesa's lavapipe, Debian package \
         mesa-vulkan-drivers, for software rendering); adapters seen: {seen}"
    )]
    NoAdapter { choice: AdapterChoice, seen: String },
    #[error(
        "adapter index {index} is out of range: the {choice} choice has {count} adapter(s), \
         numbered from 0 ({listed})"
    )]
    NoSuchIndex {
        choice: AdapterChoice,
        index: usize,
        count: usize,
        listed: String,
    },
    #[error("could not open a device on {adapter}: {source}")]
    Device {
        adapter: String,
        source: wgpu::RequestDeviceError,
    },
    #[error("GPU buffer readback failed: {0}")]
    Readback(String),
}

/// What the chosen device lets the renderer do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpuCapabilities {
    /// 64-bit `atomicMin` on storage buffers (`SHADER_INT64_ATOMIC_MIN_MAX`).
    pub int64_atomics: bool,
    /// Every 64-bit atomic on storage buffers, `atomicAdd` included
    /// (`SHADER_INT64_ATOMIC_ALL_OPS`).
    pub int64_atomic_add: bool,
    /// GPU timestamp queries around compute passes.
    pub timestamps: bool,
    /// Largest storage buffer binding in bytes.
    pub max_storage_binding_bytes: u64,
    /// Largest buffer in bytes.
    pub max_buffer_bytes: u64,
}

/// The GPU the process renders on. Create one and share it (it is `Send + Sync`).
pub struct GpuContext {
    pub adapter_info: wgpu::AdapterInfo,
    pub capabilities: GpuCapabilities,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    // Kept alive for the device's lifetime.
    _instance: wgpu::Instance,
}

impl fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.adapter_info.name)
            .field("capabilities", &self.capabilities)
            .finish_non_exhaustive()
    }
}

fn preference_rank(device_type: wgpu::DeviceType) -> u8 {
    match device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

impl GpuContext {
    /// Opens the best adapter that `choice` allows.
    pub fn new(choice: AdapterChoice) -> Result<Self, GpuError> {
        Self::with_index(choice, 0)
    }

    /// Opens adapter number `index` of those `choice` allows, best first (discrete GPUs,
    /// integrated, virtual, other, software; in the order the system lists them within each
    /// kind): one worker per GPU on a machine with several. Index 0 is [`GpuContext::new`]'s.
    pub fn with_index(choice: AdapterChoice, index: usize) -> Result<Self, GpuError> {
        // GL is left out on purpose: headless GL on llvmpipe is unreliable, and lavapipe
        // gives a software Vulkan device with 64-bit atomics.
        let backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let seen = adapters
            .iter()
            .map(|a| {
                let info = a.get_info();
                format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend)
            })
            .collect::<Vec<_>>()
            .join(", ");
        let mut accepted: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| choice.accepts(a.get_info().device_type))
            .collect();
        // Stable: adapters of one kind keep the system's order.
        accepted.sort_by_key(|a| preference_rank(a.get_info().device_type));
        if accepted.is_empty() {
            return Err(GpuError::NoAdapter {
                choice,
                seen: if seen.is_empty() { "none".into() } else { seen },
            });
        }
        let count = accepted.len();
        if index >= count {
            let listed = accepted
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    let info = a.get_info();
                    format!(
                        "{i}: {} ({:?}, {:?})",
                        info.name, info.device_type, info.backend
                    )
                })
                .collect::<Vec<_>>()
                .join(", ");
            return Err(GpuError::NoSuchIndex {
                choice,
                index,
                count,
                listed,
            });
        }
        let adapter = accepted.swap_remove(index);
        let adapter_info = adapter.get_info();

        let wanted = wgpu::Features::SHADER_INT64
            | wgpu::Features::SHADER_INT64_ATOMIC_MIN_MAX
            | wgpu::Features::SHADER_INT64_ATOMIC_ALL_OPS
            | wgpu::Features::TIMESTAMP_QUERY;
        let features = adapter.features() & wanted;
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("pointfarm"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|source| GpuError::Device {
            adapter: adapter_info.name.clone(),
            source,
        })?;

        let capabilities = GpuCapabilities {
            int64_atomics: features.contains(
                wgpu::Features::SHADER_INT64 | wgpu::Features::SHADER_INT64_ATOMIC_MIN_MAX,
            ),
            int64_atomic_add: features.contains(
                wgpu::Features::SHADER_INT64 | wgpu::Features::SHADER_INT64_ATOMIC_ALL_OPS,
            ),
            timestamps: features.contains(wgpu::Features::TIMESTAMP_QUERY),
            max_storage_binding_bytes: limits.max_storage_buffer_binding_size as u64,
            max_buffer_bytes: limits.max_buffer_size,
        };
        tracing::info!(
            adapter = %adapter_info.name,
            kind = ?adapter_info.device_type,
            backend = ?adapter_info.backend,
            driver = %adapter_info.driver,
            driver_info = %adapter_info.driver_info,
            int64_atomics = capabilities.int64_atomics,
            int64_atomic_add = capabilities.int64_atomic_add,
            timestamps = capabilities.timestamps,
            max_storage_binding_mib = capabilities.max_storage_binding_bytes >> 20,
            "GPU ready"
        );
        Ok(Self {
            adapter_info,
            capabilities,
            device,
            queue,
            _instance: instance,
        })
    }

    /// Whether the adapter is a software rasterizer (lavapipe, llvmpipe), not a GPU.
    pub fn is_software(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::Cpu
    }

    /// A one-line description for logs and CLI output.
    pub fn describe(&self) -> String {
        let info = &self.adapter_info;
        format!(
            "{} ({:?}, {:?}, {} {}; {}-bit atomics{})",
            info.name,
            info.device_type,
            info.backend,
            info.driver,
            info.driver_info,
            if self.capabilities.int64_atomics {
                64
            } else {
                32
            },
            if self.capabilities.timestamps {
                ", GPU timestamps"
            } else {
                ""
            },
        )
    }
}
