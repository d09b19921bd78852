//! Adapter and device selection.
//!
//! The device is created with the adapter's own limits, not wgpu's portable defaults: the
//! defaults cap a storage binding at 128 MiB and a buffer at 256 MiB, which is what decides how
//! big a scene fits, so asking for less than the hardware has would only waste it.

use super::GpuError;

/// Storage buffers the tracer binds in its one compute stage (see `shaders/trace.wgsl`): all
/// that WebGPU guarantees, so one layout runs on every backend, browsers included.
pub const TRACER_STORAGE_BUFFERS: u32 = 8;

/// Which graphics APIs to look for adapters on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BackendChoice {
    /// The platform's primary API (Vulkan, Metal or DX12), overridable with `WGPU_BACKEND`.
    Primary,
    /// Vulkan only: tests pin it so that a missing driver fails instead of silently falling back.
    Vulkan,
}

/// A device and queue, with what the tracer needs to know about them.
pub struct GpuContext {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// "name (backend, device type)", for reports and error messages.
    pub adapter_name: String,
    pub limits: wgpu::Limits,
}

impl GpuContext {
    /// A headless context (native only: the browser cannot block on the adapter).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless(backends: BackendChoice) -> Result<GpuContext, GpuError> {
        let instance = new_instance(backends, None);
        pollster::block_on(Self::with_instance(instance, None))
    }

    /// A context for `instance`, compatible with `surface` when given.
    pub async fn with_instance(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<GpuContext, GpuError> {
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: surface,
                apply_limit_buckets: false,
            })
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let adapter_name = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
        let limits = adapter.limits();
        if limits.max_storage_buffers_per_shader_stage < TRACER_STORAGE_BUFFERS {
            return Err(GpuError::Unsupported {
                adapter: adapter_name,
                what: format!(
                    "{} storage buffers per shader stage (the tracer binds {TRACER_STORAGE_BUFFERS})",
                    limits.max_storage_buffers_per_shader_stage
                ),
            });
        }
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("brickcast"),
                required_features: wgpu::Features::empty(),
                required_limits: limits.clone(),
                experimental_features: wgpu::ExperimentalFeatures::disabled(),
                memory_hints: wgpu::MemoryHints::Performance,
                trace: wgpu::Trace::Off,
            })
            .await
            .map_err(|e| GpuError::Device {
                adapter: adapter_name.clone(),
                reason: e.to_string(),
            })?;
        Ok(GpuContext {
            instance,
            adapter,
            device,
            queue,
            adapter_name,
            limits,
        })
    }

    /// Largest storage binding the device accepts, in bytes.
    pub fn max_binding_bytes(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Waits until all submitted work is done (in a browser, where nothing can block, this only
    /// hands the queue a poll; completion arrives through the event loop).
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Device {
                adapter: self.adapter_name.clone(),
                reason: e.to_string(),
            })
    }
}

/// An instance for `backends`, with a display handle when it will present to a window.
pub fn new_instance(
    backends: BackendChoice,
    display: Option<Box<dyn wgpu::wgt::WgpuHasDisplayHandle>>,
) -> wgpu::Instance {
    let mut desc = match display {
        Some(display) => wgpu::InstanceDescriptor::new_with_display_handle_from_env(display),
        None => wgpu::InstanceDescriptor::new_without_display_handle_from_env(),
    };
    desc.backends = match backends {
        BackendChoice::Vulkan => wgpu::Backends::VULKAN,
        BackendChoice::Primary => wgpu::Backends::from_env().unwrap_or(wgpu::Backends::PRIMARY),
    };
    wgpu::Instance::new(desc)
}
