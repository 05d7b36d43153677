//! Which graphics backend and adapter the renderer runs on ([`BackendPreference`],
//! [`RendererConfig`]), and the instances kept for the life of the process.

use std::sync::Mutex;

/// Which graphics backends the renderer may use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BackendPreference {
    /// A GPU through Vulkan; otherwise OpenGL (a GPU without a Vulkan driver, or Mesa's CPU
    /// renderer llvmpipe, which measured faster than lavapipe); otherwise lavapipe.
    #[default]
    Auto,
    /// Vulkan only.
    Vulkan,
    /// OpenGL (EGL) only.
    Gl,
}

impl BackendPreference {
    /// The names a preference is written as, one per variant: `auto`, `vulkan`, `gl`.
    pub const NAMES: [&'static str; 3] = ["auto", "vulkan", "gl"];

    /// The preference named by `ESRP_RENDER_BACKEND` (`auto`, `vulkan` or `gl`), if set and
    /// valid.
    pub fn from_env() -> Option<Self> {
        std::env::var("ESRP_RENDER_BACKEND").ok()?.parse().ok()
    }

    /// Its name: `auto`, `vulkan` or `gl`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Vulkan => "vulkan",
            Self::Gl => "gl",
        }
    }
}

impl std::fmt::Display for BackendPreference {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`BackendPreference`].
#[derive(Debug, thiserror::Error)]
#[error("unknown render backend {0:?}: use auto, vulkan or gl")]
pub struct UnknownBackend(pub String);

impl std::str::FromStr for BackendPreference {
    type Err = UnknownBackend;

    /// `auto`, `vulkan` or `gl` (also `gles`, `opengl`), in any case.
    fn from_str(name: &str) -> Result<Self, UnknownBackend> {
        match name.to_ascii_lowercase().as_str() {
            "auto" => Ok(Self::Auto),
            "vulkan" => Ok(Self::Vulkan),
            "gl" | "gles" | "opengl" => Ok(Self::Gl),
            _ => Err(UnknownBackend(name.to_owned())),
        }
    }
}

/// How to create a [`Renderer`](crate::Renderer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RendererConfig {
    /// Which backends to try.
    pub backends: BackendPreference,
    /// Prefer a discrete GPU (`HighPerformance`) or an integrated one.
    pub power_preference: wgpu::PowerPreference,
    /// Largest side of the atlas texture, pixels (rounded down to a power of two and capped by
    /// the adapter). 4096 holds 1024 views of 128×128.
    pub max_atlas_size: u32,
    /// Skip the pieces of a scene (floor, wall pieces, objects) that an egocentric view cannot
    /// see, by their bounding spheres: less vertex work, the same images bit for bit. `false`
    /// draws every piece in every view (for comparison).
    pub cull: bool,
    /// What draws the triangles: the graphics pipeline, or compute shaders.
    pub rasterizer: Rasterizer,
    /// Whether to time each batch's drawing on the device's own clock (two timestamp queries
    /// a batch, read back with its images: [`RenderTimings::gpu`](crate::RenderTimings::gpu)),
    /// where the adapter has timestamp queries.
    pub timestamps: Timestamps,
    /// The depth buffers of the graphics pipeline's passes (one pass per view).
    pub depth_buffers: DepthBuffers,
}

impl Default for RendererConfig {
    fn default() -> Self {
        Self {
            backends: BackendPreference::Auto,
            power_preference: wgpu::PowerPreference::HighPerformance,
            max_atlas_size: 4096,
            cull: true,
            rasterizer: Rasterizer::Pipeline,
            timestamps: Timestamps::Auto,
            depth_buffers: DepthBuffers::Shared,
        }
    }
}

/// The depth buffers the graphics pipeline's passes draw with: each view of a batch has a pass
/// of its own (its page). The images are the same either way.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DepthBuffers {
    /// One buffer that every pass clears in turn: the least memory, and a depth buffer that
    /// stays in a CPU renderer's caches; on a GPU, each pass waits for the one before it to
    /// finish its depth writes.
    #[default]
    Shared,
    /// A layer per page (4 bytes a pixel a page more): no pass waits for another's depth
    /// writes, so a GPU may draw a batch's views at once.
    PerPage,
}

impl DepthBuffers {
    /// The names it is written as, one per variant: `shared`, `per-page`.
    pub const NAMES: [&'static str; 2] = ["shared", "per-page"];

    /// Its name: `shared` or `per-page`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Shared => "shared",
            Self::PerPage => "per-page",
        }
    }
}

impl std::fmt::Display for DepthBuffers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`DepthBuffers`] setting.
#[derive(Debug, thiserror::Error)]
#[error("unknown depth buffers setting {0:?}: use shared or per-page")]
pub struct UnknownDepthBuffers(pub String);

impl std::str::FromStr for DepthBuffers {
    type Err = UnknownDepthBuffers;

    /// `shared` or `per-page`, in any case.
    fn from_str(name: &str) -> Result<Self, UnknownDepthBuffers> {
        match name.to_ascii_lowercase().as_str() {
            "shared" => Ok(Self::Shared),
            "per-page" => Ok(Self::PerPage),
            _ => Err(UnknownDepthBuffers(name.to_owned())),
        }
    }
}

/// Whether a renderer times its device's drawing with timestamp queries (where the adapter has
/// them; without, it never does).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Timestamps {
    /// On a GPU, not on a CPU renderer (lavapipe, llvmpipe): there the device's drawing is the
    /// submitting threads' own time, which the stages already show, and lavapipe's timestamps
    /// cost about 70 µs a batch (docs/performance.md).
    #[default]
    Auto,
    /// Always.
    On,
    /// Never.
    Off,
}

impl Timestamps {
    /// The names it is written as, one per variant: `auto`, `on`, `off`.
    pub const NAMES: [&'static str; 3] = ["auto", "on", "off"];

    /// Its name: `auto`, `on` or `off`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::On => "on",
            Self::Off => "off",
        }
    }

    /// Whether an adapter of `device_type` is timed.
    pub fn wanted(self, device_type: wgpu::DeviceType) -> bool {
        match self {
            Self::Auto => device_type != wgpu::DeviceType::Cpu,
            Self::On => true,
            Self::Off => false,
        }
    }
}

impl std::fmt::Display for Timestamps {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`Timestamps`] setting.
#[derive(Debug, thiserror::Error)]
#[error("unknown timestamps setting {0:?}: use auto, on or off")]
pub struct UnknownTimestamps(pub String);

impl std::str::FromStr for Timestamps {
    type Err = UnknownTimestamps;

    /// `auto`, `on` or `off`, in any case.
    fn from_str(name: &str) -> Result<Self, UnknownTimestamps> {
        match name.to_ascii_lowercase().as_str() {
            "auto" => Ok(Self::Auto),
            "on" => Ok(Self::On),
            "off" => Ok(Self::Off),
            _ => Err(UnknownTimestamps(name.to_owned())),
        }
    }
}

/// What draws a view's triangles.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Rasterizer {
    /// The graphics pipeline (vertex and fragment shaders, the device's rasteriser and depth
    /// test).
    #[default]
    Pipeline,
    /// Compute shaders (`raster.wgsl`): the same images up to the rounding of edges and depth,
    /// drawn on the device's compute units, for devices with little fixed-function graphics
    /// hardware (datacenter GPUs such as the H100 and H200). Needs compute shaders and storage
    /// buffers (Vulkan, OpenGL ES 3.1).
    Compute,
}

impl Rasterizer {
    /// The names a rasteriser is written as, one per variant: `pipeline`, `compute`.
    pub const NAMES: [&'static str; 2] = ["pipeline", "compute"];

    /// Its name: `pipeline` or `compute`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Pipeline => "pipeline",
            Self::Compute => "compute",
        }
    }
}

impl std::fmt::Display for Rasterizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`Rasterizer`].
#[derive(Debug, thiserror::Error)]
#[error("unknown rasterizer {0:?}: use pipeline or compute")]
pub struct UnknownRasterizer(pub String);

impl std::str::FromStr for Rasterizer {
    type Err = UnknownRasterizer;

    /// `pipeline` or `compute`, in any case.
    fn from_str(name: &str) -> Result<Self, UnknownRasterizer> {
        match name.to_ascii_lowercase().as_str() {
            "pipeline" => Ok(Self::Pipeline),
            "compute" => Ok(Self::Compute),
            _ => Err(UnknownRasterizer(name.to_owned())),
        }
    }
}

/// The first instance of each backend that found an adapter, kept until the process exits so
/// that the graphics driver it loaded stays loaded.
///
/// Dropping the last instance of a backend makes the driver stack unload Mesa's driver while
/// the process goes on: wgpu terminates the EGL display when its last OpenGL instance goes, and
/// Mesa's EGL then closes `swrast_dri.so` (llvmpipe); the Vulkan loader closes lavapipe's ICD
/// with the last `VkInstance`. Mesa 22.3's driver stack leaves an exit handler behind that
/// points into the unloaded code, so a process that had dropped its last renderer died in
/// `exit` with SIGSEGV, or with heap corruption (`corrupted size vs. prev_size in fastbins`,
/// `double free or corruption (out)`) where that memory had been reused: esrp-server after
/// about one SIGTERM in ten. With one instance per backend held for good, no driver is unloaded
/// early and each tears down in its own order at exit. Dropped renderers still release their
/// devices, buffers, textures and pipelines; what stays is one instance (for OpenGL, one EGL
/// context) per backend used.
pub(super) static KEPT_INSTANCES: Mutex<Vec<(wgpu::Backend, wgpu::Instance)>> = Mutex::new(Vec::new());

pub(super) fn request_adapter(backends: wgpu::Backends, power: wgpu::PowerPreference) -> Option<wgpu::Adapter> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends,
        flags: wgpu::InstanceFlags::from_build_config().with_env(),
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    let options = wgpu::RequestAdapterOptions { power_preference: power, ..Default::default() };
    let adapter = pollster::block_on(instance.request_adapter(&options)).ok()?;
    let backend = adapter.get_info().backend;
    let mut kept = KEPT_INSTANCES.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    if !kept.iter().any(|(b, _)| *b == backend) {
        kept.push((backend, instance));
    }
    Some(adapter)
}
