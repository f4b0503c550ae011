//! Choosing and opening a GPU: one [`GpuContext`] per process, shared by every kernel on it.

use std::fmt;
use std::str::FromStr;
use std::sync::Arc;

use thiserror::Error;

/// Where a worker (or `nephele render` / `bench`) runs its kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceChoice {
    /// A hardware GPU if the machine has one, else the CPU. A software adapter (Mesa's
    /// lavapipe) is never picked by `auto`: it is slower than the CPU kernels.
    #[default]
    Auto,
    /// The CPU kernels (SIMD per `--simd`).
    Cpu,
    /// A GPU: hardware if present, else a software Vulkan adapter (labelled as such); an
    /// error if there is none.
    Gpu,
}

impl DeviceChoice {
    pub const VALUES: &'static [&'static str] = &["auto", "cpu", "gpu"];
}

impl FromStr for DeviceChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<DeviceChoice, String> {
        match s {
            "auto" => Ok(DeviceChoice::Auto),
            "cpu" => Ok(DeviceChoice::Cpu),
            "gpu" => Ok(DeviceChoice::Gpu),
            other => Err(format!("unknown device {other:?} (expected one of: {})", DeviceChoice::VALUES.join(", "))),
        }
    }
}

impl fmt::Display for DeviceChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DeviceChoice::Auto => "auto",
            DeviceChoice::Cpu => "cpu",
            DeviceChoice::Gpu => "gpu",
        })
    }
}

#[derive(Debug, Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (looked for Vulkan adapters; adapters seen: {seen}). Install a GPU driver, or \
         Mesa's software Vulkan (Debian: mesa-vulkan-drivers) to run the GPU kernels on the CPU, or use --device cpu"
    )]
    NoAdapter { seen: String },
    #[error("the GPU refused a device: {0}")]
    Device(String),
    #[error("the asset does not fit this GPU: {0}")]
    TooLarge(String),
    #[error("the GPU kernel does not support this asset: {0}")]
    Unsupported(String),
    #[error("GPU validation failed: {0}")]
    Validation(String),
    #[error("reading results back from the GPU failed: {0}")]
    Readback(String),
}

/// An open GPU device and its queue.
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
}

impl fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuContext").field("adapter", &self.label()).finish()
    }
}

fn is_software(info: &wgpu::AdapterInfo) -> bool {
    info.device_type == wgpu::DeviceType::Cpu
}

impl GpuContext {
    /// Opens the device `choice` asks for: `None` for the CPU (asked, or `auto` without a
    /// hardware GPU).
    pub fn open(choice: DeviceChoice) -> Result<Option<Arc<GpuContext>>, GpuError> {
        if choice == DeviceChoice::Cpu {
            return Ok(None);
        }
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends: wgpu::Backends::VULKAN,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
        let seen = || {
            let names: Vec<String> = adapters.iter().map(|a| describe(&a.get_info())).collect();
            if names.is_empty() { "none".to_string() } else { names.join("; ") }
        };
        // Hardware first (discrete before integrated), software last.
        let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
            wgpu::DeviceType::DiscreteGpu => 0,
            wgpu::DeviceType::IntegratedGpu => 1,
            wgpu::DeviceType::VirtualGpu | wgpu::DeviceType::Other => 2,
            wgpu::DeviceType::Cpu => 3,
        };
        let best = adapters.iter().min_by_key(|a| rank(a));
        let adapter = match (choice, best) {
            (_, None) if choice == DeviceChoice::Auto => return Ok(None),
            (_, None) => return Err(GpuError::NoAdapter { seen: seen() }),
            (DeviceChoice::Auto, Some(a)) if is_software(&a.get_info()) => {
                tracing::info!(adapters = %seen(), "device auto: only a software GPU adapter; using the CPU kernels");
                return Ok(None);
            }
            (_, Some(a)) => a,
        };
        let info = adapter.get_info();
        if is_software(&info) {
            tracing::warn!(adapter = %describe(&info), "running the GPU kernels on a software adapter (slower than the CPU kernels)");
        }
        // Take what the adapter offers: big assets need large storage bindings.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("nephele"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        device.on_uncaptured_error(Arc::new(|e: wgpu::Error| tracing::error!(error = %e, "uncaptured GPU error")));
        Ok(Some(Arc::new(GpuContext { device, queue, info, limits })))
    }

    /// Adapter name, backend and whether it is a software adapter, for logs and reports.
    pub fn label(&self) -> String {
        describe(&self.info)
    }

    /// Whether this is a software adapter (Mesa's lavapipe): figures from it are not GPU
    /// figures.
    pub fn is_software(&self) -> bool {
        is_software(&self.info)
    }

    pub(crate) fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }
}

fn describe(info: &wgpu::AdapterInfo) -> String {
    let kind = if is_software(info) { ", software" } else { "" };
    format!("{} ({:?}{kind})", info.name, info.backend)
}
