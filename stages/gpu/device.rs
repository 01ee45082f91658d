//! The wgpu adapter and device: one per process, shared by every stage and worker.

use std::any::{Any, TypeId};
use std::collections::HashMap;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, OnceLock};

/// An open device and what the kernels need to know about it.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// The first validation or device error wgpu reported since the last [`Gpu::check`]
    /// (wgpu's default is to panic on them; we turn them into errors).
    errors: Arc<Mutex<Option<String>>>,
    /// Kernels compiled for this device, by their host type ([`Gpu::compiled`]).
    compiled: Mutex<HashMap<TypeId, Arc<dyn Any + Send + Sync>>>,
}

/// How to open a device.
#[derive(Debug, Clone, Copy)]
pub struct GpuOptions {
    /// wgpu backends to look at (this build compiles Vulkan only).
    pub backends: wgpu::Backends,
}

impl GpuOptions {
    /// Vulkan, or what wgpu's `WGPU_BACKEND` environment variable names (e.g. `WGPU_BACKEND=gl`
    /// in this Vulkan-only build: no adapter, which is how the tests force the CPU fallback).
    pub fn from_env() -> GpuOptions {
        GpuOptions { backends: wgpu::Backends::VULKAN.with_env() }
    }
}

impl Gpu {
    /// Opens the best adapter `options` allow (a discrete GPU before an integrated one before
    /// a software renderer). The error says why none could be opened.
    pub fn open(options: GpuOptions) -> Result<Gpu, String> {
        // wgpu panics on an instance with no compiled backend (this build has Vulkan only,
        // which e.g. macOS lacks): say so instead.
        if wgpu::Instance::enabled_backend_features().is_empty() {
            return Err("this build has no wgpu backend for this platform (it compiles Vulkan only)".into());
        }
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = options.backends;
        let instance = wgpu::Instance::new(desc);
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| format!("{e} (wgpu backends tried: {:?})", options.backends))?;
        let info = adapter.get_info();
        // The adapter's own limits: a CT volume or a large lattice needs more than WebGPU's
        // defaults, and the kernels check sizes against these before they allocate.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("aret-pipe"),
            // Nothing beyond WebGPU's core: the gradient scatter adds integers, not floats.
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| format!("adapter {} would not open a device: {e}", info.name))?;
        let errors = Arc::new(Mutex::new(None::<String>));
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut first) = sink.lock() {
                first.get_or_insert_with(|| e.to_string());
            }
        }));
        Ok(Gpu { device, queue, info, limits, errors, compiled: Mutex::new(HashMap::new()) })
    }

    /// The process's device (opened on first use from [`GpuOptions::from_env`]), or why there is none.
    pub fn shared() -> Result<Arc<Gpu>, String> {
        static SHARED: OnceLock<Result<Arc<Gpu>, String>> = OnceLock::new();
        SHARED.get_or_init(|| Gpu::open(GpuOptions::from_env()).map(Arc::new)).clone()
    }

    /// A software renderer (lavapipe/llvmpipe, SwiftShader): correct, but slower than the CPU backend.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The adapter in words, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan, Cpu)`.
    pub fn describe(&self) -> String {
        format!("{} ({:?}, {:?})", self.info.name, self.info.backend, self.info.device_type)
    }

    /// Fails with the first error wgpu reported since the last check.
    pub fn check(&self) -> anyhow::Result<()> {
        match self.errors.lock().ok().and_then(|mut e| e.take()) {
            Some(e) => anyhow::bail!("GPU ({}): {e}", self.info.name),
            None => Ok(()),
        }
    }

    /// Blocks until the queue is idle, then [`Gpu::check`]s.
    pub fn wait(&self) -> anyhow::Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| anyhow::anyhow!("GPU ({}): {e}", self.info.name))?;
        self.check()
    }

    /// The kernels of host type `T`, compiled by `build` once per device and shared after.
    pub(crate) fn compiled<T: Any + Send + Sync>(
        &self,
        build: impl FnOnce(&Gpu) -> anyhow::Result<T>,
    ) -> anyhow::Result<Arc<T>> {
        let mut compiled = self.compiled.lock().map_err(|_| anyhow::anyhow!("a GPU kernel build panicked"))?;
        let kernels = match compiled.get(&TypeId::of::<T>()) {
            Some(kernels) => kernels.clone(),
            None => {
                let kernels: Arc<dyn Any + Send + Sync> = Arc::new(build(self)?);
                compiled.insert(TypeId::of::<T>(), kernels.clone());
                kernels
            }
        };
        Ok(kernels.downcast::<T>().expect("kernels are stored under their own type"))
    }
}

/// The submissions a loop keeps ahead of the device: after `limit` are in flight, `submit`
/// waits for the oldest, which bounds the staging memory of per-step uploads (no data comes
/// back). The VM fit's loop and the dense fit's share it.
pub struct InFlight {
    limit: usize,
    submitted: VecDeque<wgpu::SubmissionIndex>,
}

impl InFlight {
    pub fn new(limit: usize) -> InFlight {
        InFlight { limit, submitted: VecDeque::new() }
    }

    /// Submits `encoder` on `gpu`'s queue, then waits for the oldest submission if too many are in flight.
    pub fn submit(&mut self, gpu: &Gpu, encoder: wgpu::CommandEncoder) -> anyhow::Result<()> {
        self.submitted.push_back(gpu.queue.submit([encoder.finish()]));
        if self.submitted.len() > self.limit {
            let oldest = self.submitted.pop_front().expect("non-empty");
            let wait = wgpu::PollType::Wait { submission_index: Some(oldest), timeout: None };
            gpu.device.poll(wait).map_err(|e| anyhow::anyhow!("GPU ({}): {e}", gpu.info.name))?;
            gpu.check()?;
        }
        Ok(())
    }
}
