//! The long-lived [`Renderer`]: device, queue, pipelines, scene uploads and batched rendering
//! into an atlas.
//!
//! # Concurrency
//!
//! [`Renderer`] is `Send + Sync`. [`Renderer::render_batch`] takes `&self`; each batch takes an
//! atlas (textures, uniform buffer, readback buffer, reused from batch to batch) out of a small
//! pool under a mutex, renders with it alone, waits for its own submission and puts it back. So
//! batches on a few threads overlap — one encodes and submits while another waits for the
//! device or extracts pixels — and outputs never depend on what else is being rendered. The
//! intended use is one or two dedicated render threads that gather view requests into large
//! batches.
//! [`Renderer::upload_scene`] does not take that mutex and may run on any thread.

use std::num::NonZeroU64;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use bytes::Bytes;
use esrp_core::{CompiledScene, ObjectPose};
use wgpu::util::DeviceExt;

use crate::camera::{Camera, EgoFrustum, TopDownFrame, ego_view, top_down_view};
use crate::error::RenderError;
use crate::gpu::{GpuVertex, GpuView, MAX_POSE_SLOTS, SHADER_SOURCE, VIEW_STRIDE};
use crate::mesh::{BACKGROUND_COLOUR, MeshPart, build_scene_mesh};

/// Resolution of every view unless a request asks for another (SPEC §2, §4).
pub const DEFAULT_RESOLUTION: u32 = 128;
/// Most views drawn with one submit (1024 views of 128×128, fewer of larger views): a
/// [`Renderer::render_batch`] of more is drawn in consecutive chunks. Callers that gather work
/// for the renderer may use it as the size worth gathering; it is not a limit.
pub const CHUNK_VIEWS: usize = 1024;
/// Most page pixels drawn with one submit (1024 views of 128×128); a single view larger than
/// this is drawn alone.
pub const CHUNK_PIXELS: u64 = 1 << 24;
/// Most movable objects a scene may have for this renderer (pose slots on the GPU).
pub const MAX_MOVABLE_OBJECTS: usize = MAX_POSE_SLOTS - 1;

const COLOUR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// View depth as the bits of an `f32` (R32Float is not renderable on OpenGL ES).
const DEPTH_OUT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
const SEGMENT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
/// Atlas textures kept for reuse (one per distinct size and output set).
const CACHED_ATLASES: usize = 4;

static NEXT_RENDERER_ID: AtomicU64 = AtomicU64::new(1);

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

/// How to create a [`Renderer`].
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
}

impl Default for RendererConfig {
    fn default() -> Self {
        Self {
            backends: BackendPreference::Auto,
            power_preference: wgpu::PowerPreference::HighPerformance,
            max_atlas_size: 4096,
            cull: true,
        }
    }
}

/// A scene's geometry on the device, uploaded once by [`Renderer::upload_scene`] and shared by
/// every view of every episode of that scene (wrap it in an `Arc`; caching by scene id is the
/// caller's job).
#[derive(Debug)]
pub struct SceneHandle {
    renderer_id: u64,
    scene_id: String,
    vertex_buffer: wgpu::Buffer,
    index_buffer: wgpu::Buffer,
    index_count: u32,
    parts: Vec<MeshPart>,
    vertex_count: usize,
    movable_count: usize,
    frame: TopDownFrame,
    max_height: f64,
}

impl SceneHandle {
    /// The scene's id.
    pub fn scene_id(&self) -> &str {
        &self.scene_id
    }

    /// Number of movable objects: the length every view's `object_poses` must have.
    pub fn movable_count(&self) -> usize {
        self.movable_count
    }

    /// Number of triangles drawn per view.
    pub fn triangle_count(&self) -> usize {
        self.index_count as usize / 3
    }

    /// Number of vertices on the device.
    pub fn vertex_count(&self) -> usize {
        self.vertex_count
    }

    /// The top-down view's frame at `resolution` (same as [`TopDownFrame::for_scene`]).
    pub fn top_down_frame(&self, resolution: u32) -> TopDownFrame {
        self.frame.with_resolution(resolution)
    }
}

/// Which images a view produces besides RGB.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Outputs {
    /// View depth in metres (`f32`), [`f32::INFINITY`] where nothing is drawn.
    pub depth: bool,
    /// Instance segmentation ([`crate::SegmentLabel`] ids).
    pub segmentation: bool,
}

impl Outputs {
    /// RGB only.
    pub const RGB: Outputs = Outputs { depth: false, segmentation: false };
    /// RGB, depth and segmentation.
    pub const ALL: Outputs = Outputs { depth: true, segmentation: true };

    fn any_extra(self) -> bool {
        self.depth || self.segmentation
    }
}

/// One view to render.
#[derive(Clone, Copy, Debug)]
pub struct ViewRequest<'a> {
    /// The scene, uploaded by the same renderer.
    pub scene: &'a SceneHandle,
    /// The camera.
    pub camera: Camera,
    /// One pose per movable object, in scene order: current poses for the egocentric and
    /// current top-down views, target poses for the goal image.
    pub object_poses: &'a [ObjectPose],
    /// Extra images wanted.
    pub outputs: Outputs,
    /// Width and height, pixels.
    pub resolution: u32,
}

impl<'a> ViewRequest<'a> {
    /// An RGB view at [`DEFAULT_RESOLUTION`].
    pub fn new(scene: &'a SceneHandle, camera: Camera, object_poses: &'a [ObjectPose]) -> Self {
        Self { scene, camera, object_poses, outputs: Outputs::RGB, resolution: DEFAULT_RESOLUTION }
    }

    /// The same view with other outputs.
    pub fn with_outputs(self, outputs: Outputs) -> Self {
        Self { outputs, ..self }
    }

    /// The same view at another resolution.
    pub fn with_resolution(self, resolution: u32) -> Self {
        Self { resolution, ..self }
    }
}

/// The images of one view. All are row-major, top row first, `resolution × resolution`.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewOutput {
    /// Width and height, pixels.
    pub resolution: u32,
    /// Tightly packed RGB, 3 bytes per pixel.
    pub rgb: Bytes,
    /// View depth in metres along the camera's axis, if asked for; [`f32::INFINITY`] where
    /// nothing is drawn.
    pub depth: Option<Vec<f32>>,
    /// Segmentation ids ([`crate::SegmentLabel::id`]), if asked for.
    pub segmentation: Option<Vec<u32>>,
}

/// Where one view lies in the atlas.
#[derive(Clone, Copy, Debug)]
struct Tile {
    page: u32,
    x: u32,
    y: u32,
    size: u32,
}

/// A texture array (one layer per page) and a view of each layer.
struct PagedTexture {
    texture: wgpu::Texture,
    layers: Vec<wgpu::TextureView>,
}

/// Textures and readback buffer of one atlas shape: `pages` square pages of `side` pixels.
///
/// Pages rather than one big texture: lavapipe's cost of a render pass grows with the area of
/// its target, so views go into small pages, one render pass each, all in one submit, one copy
/// and one map.
struct Atlas {
    side: u32,
    pages: u32,
    full: bool,
    colour: PagedTexture,
    /// One page of depth buffer, cleared by every pass.
    depth: wgpu::TextureView,
    /// View depth (as f32 bits) and segmentation targets, present when `full`.
    extras: Option<[PagedTexture; 2]>,
    readback: wgpu::Buffer,
    /// Per-view uniforms (one `VIEW_STRIDE` slot per page) and their bind group.
    uniforms: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    last_used: u64,
}

impl Atlas {
    fn page_bytes(&self) -> u64 {
        u64::from(self.side) * u64::from(self.side) * 4
    }

    fn plane_bytes(&self) -> u64 {
        self.page_bytes() * u64::from(self.pages)
    }
}

/// The atlases not in use right now. A batch takes one out (or makes one), renders with it
/// without holding the lock, and puts it back: batches on different threads overlap (one
/// encodes and submits while another waits for the device or extracts its pixels).
struct BatchState {
    atlases: Vec<Atlas>,
    batches: u64,
}

/// The renderer: one per process, long-lived. See the module docs for its concurrency.
pub struct Renderer {
    id: u64,
    adapter_info: wgpu::AdapterInfo,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline_rgb: wgpu::RenderPipeline,
    pipeline_full: wgpu::RenderPipeline,
    bind_group_layout: wgpu::BindGroupLayout,
    max_atlas: u32,
    max_pages: u32,
    cull: bool,
    lost: Arc<Mutex<Option<String>>>,
    state: Mutex<BatchState>,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("adapter", &self.adapter_info.name)
            .field("backend", &self.adapter_info.backend)
            .finish()
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
static KEPT_INSTANCES: Mutex<Vec<(wgpu::Backend, wgpu::Instance)>> = Mutex::new(Vec::new());

fn request_adapter(backends: wgpu::Backends, power: wgpu::PowerPreference) -> Option<wgpu::Adapter> {
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

impl Renderer {
    /// Creates the device, the pipelines and the uniform buffer, and logs the adapter.
    ///
    /// Fails with [`RenderError::NoAdapter`] (never panics) when no adapter exists.
    pub fn new(config: RendererConfig) -> Result<Self, RenderError> {
        let power = config.power_preference;
        let (adapter, tried) = match config.backends {
            BackendPreference::Auto => {
                // A GPU through Vulkan first. Without one, both APIs reach Mesa's CPU
                // rasteriser: OpenGL (llvmpipe) draws in the calling thread where Vulkan
                // (lavapipe) hands every submission to a queue thread, and measured faster
                // end to end (README), so it comes before lavapipe.
                let adapter = match request_adapter(wgpu::Backends::VULKAN, power) {
                    Some(vulkan) if vulkan.get_info().device_type != wgpu::DeviceType::Cpu => Some(vulkan),
                    vulkan => request_adapter(wgpu::Backends::GL, power).or(vulkan),
                };
                (adapter, "vulkan, gl")
            }
            BackendPreference::Vulkan => (request_adapter(wgpu::Backends::VULKAN, power), "vulkan"),
            BackendPreference::Gl => (request_adapter(wgpu::Backends::GL, power), "gl"),
        };
        let adapter = adapter.ok_or_else(|| RenderError::NoAdapter { tried: tried.to_owned() })?;
        let adapter_info = adapter.get_info();
        log::info!(
            "esrp-render: adapter {} ({:?}, {:?}, driver {} {})",
            adapter_info.name,
            adapter_info.backend,
            adapter_info.device_type,
            adapter_info.driver,
            adapter_info.driver_info
        );
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("esrp-render"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| RenderError::RequestDevice { adapter: adapter_info.name.clone(), reason: e.to_string() })?;

        let lost = Arc::new(Mutex::new(None));
        let lost_flag = Arc::clone(&lost);
        device.set_device_lost_callback(move |reason, message| {
            if let Ok(mut slot) = lost_flag.lock() {
                *slot = Some(format!("{reason:?}: {message}"));
            }
        });

        // Errors are returned from the operations that cause them (error scopes); anything else
        // is logged rather than aborting the process, as wgpu does by default.
        device.on_uncaptured_error(Arc::new(|error| log::error!("esrp-render: uncaptured wgpu error: {error}")));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);

        let max_side = config.max_atlas_size.min(limits.max_texture_dimension_2d).max(64);
        let max_atlas = 1u32 << (31 - max_side.leading_zeros());

        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("esrp-render shader"),
            source: wgpu::ShaderSource::Wgsl(SHADER_SOURCE.into()),
        });
        let bind_group_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("esrp-render view"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: NonZeroU64::new(std::mem::size_of::<GpuView>() as u64),
                },
                count: None,
            }],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("esrp-render"),
            bind_group_layouts: &[Some(&bind_group_layout)],
            immediate_size: 0,
        });
        let pipeline = |vs: &str, fs: &str, targets: &[Option<wgpu::ColorTargetState>]| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(vs),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some(vs),
                    compilation_options: Default::default(),
                    buffers: &[Some(GpuVertex::layout())],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    front_face: wgpu::FrontFace::Ccw,
                    cull_mode: Some(wgpu::Face::Back),
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Greater),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(fs),
                    compilation_options: Default::default(),
                    targets,
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let target = |format| Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL });
        let pipeline_rgb = pipeline("vs_rgb", "fs_rgb", &[target(COLOUR_FORMAT)]);
        let pipeline_full =
            pipeline("vs_full", "fs_full", &[target(COLOUR_FORMAT), target(DEPTH_OUT_FORMAT), target(SEGMENT_FORMAT)]);

        if let Some(error) = pollster::block_on(scope.pop()) {
            return Err(RenderError::RequestDevice {
                adapter: adapter_info.name.clone(),
                reason: format!("the adapter cannot build the pipelines: {error}"),
            });
        }

        Ok(Self {
            id: NEXT_RENDERER_ID.fetch_add(1, Ordering::Relaxed),
            adapter_info,
            device,
            queue,
            pipeline_rgb,
            pipeline_full,
            bind_group_layout,
            max_atlas,
            max_pages: limits.max_texture_array_layers.clamp(1, CHUNK_VIEWS as u32),
            cull: config.cull,
            lost,
            state: Mutex::new(BatchState { atlases: Vec::new(), batches: 0 }),
        })
    }

    /// The adapter in use (name, backend, driver).
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.adapter_info
    }

    /// Whether the adapter is a CPU rasteriser (lavapipe, llvmpipe).
    pub fn is_software(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::Cpu
    }

    /// Largest resolution of one view.
    pub fn max_resolution(&self) -> u32 {
        self.max_atlas
    }

    /// Builds a scene's triangle mesh and uploads it. Do this once per scene and share the
    /// handle (it is `Send + Sync`).
    pub fn upload_scene(&self, scene: &CompiledScene) -> Result<Arc<SceneHandle>, RenderError> {
        let movable_count = scene.scene().movable_objects.len();
        if movable_count > MAX_MOVABLE_OBJECTS {
            return Err(RenderError::TooManyObjects {
                scene: scene.scene().id.clone(),
                count: movable_count,
                max: MAX_MOVABLE_OBJECTS,
            });
        }
        let mesh = build_scene_mesh(scene)?;
        let mut vertices = mesh.vertices;
        let mut indices = mesh.indices;
        let index_count = indices.len() as u32;
        // wgpu buffers cannot be empty; an empty scene draws nothing anyway.
        if vertices.is_empty() {
            vertices.push(bytemuck::Zeroable::zeroed());
        }
        if indices.is_empty() {
            indices.push(0);
        }
        let vertex_buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("esrp-render scene vertices"),
            contents: bytemuck::cast_slice(&vertices),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let index_buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("esrp-render scene indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::INDEX,
        });
        Ok(Arc::new(SceneHandle {
            renderer_id: self.id,
            scene_id: scene.scene().id.clone(),
            vertex_buffer,
            index_buffer,
            index_count,
            parts: mesh.parts,
            vertex_count: vertices.len(),
            movable_count,
            frame: TopDownFrame::for_scene(scene, DEFAULT_RESOLUTION),
            max_height: mesh.max_height,
        }))
    }

    /// Renders one view (a batch of one).
    pub fn render_one(&self, request: &ViewRequest<'_>) -> Result<ViewOutput, RenderError> {
        let mut out = self.render_batch(std::slice::from_ref(request))?;
        out.pop().ok_or_else(|| RenderError::Readback { reason: "no output for the view".into() })
    }

    fn validate(&self, requests: &[ViewRequest<'_>]) -> Result<(), RenderError> {
        for (view, request) in requests.iter().enumerate() {
            if request.scene.renderer_id != self.id {
                return Err(RenderError::ForeignScene { view });
            }
            if request.resolution == 0 || request.resolution > self.max_atlas {
                return Err(RenderError::InvalidResolution { resolution: request.resolution, max: self.max_atlas });
            }
            if request.object_poses.len() != request.scene.movable_count {
                return Err(RenderError::InvalidPoses {
                    view,
                    reason: format!(
                        "{} poses given for a scene with {} movable objects",
                        request.object_poses.len(),
                        request.scene.movable_count
                    ),
                });
            }
            if request.object_poses.iter().any(|p| !(p.x.is_finite() && p.z.is_finite() && p.yaw.is_finite())) {
                return Err(RenderError::InvalidPoses { view, reason: "a pose is not finite".into() });
            }
            if let Camera::Ego(camera) = request.camera {
                let finite = camera.eye.iter().all(|c| c.is_finite())
                    && camera.yaw.is_finite()
                    && camera.pitch.is_finite()
                    && camera.horizontal_fov > 0.0
                    && camera.horizontal_fov < std::f64::consts::PI;
                if !finite {
                    return Err(RenderError::InvalidPoses {
                        view,
                        reason: "the egocentric camera is not finite or its field of view is not in (0, π)".into(),
                    });
                }
            }
        }
        Ok(())
    }

    /// One page per view, every view at the page's origin: the viewport transform, and so
    /// every rounding of rasterisation and interpolation, is the same whatever else is in the
    /// batch. Returns the tiles (in request order), the page side (the largest resolution
    /// rounded up to 64, so that rows are 256-byte aligned) and the number of pages (a power of
    /// two, so that atlas shapes repeat across batches). `requests` fits one chunk.
    fn layout(&self, requests: &[ViewRequest<'_>]) -> (Vec<Tile>, u32, u32) {
        let largest = requests.iter().map(|r| r.resolution).max().unwrap_or(1);
        let side = largest.next_multiple_of(64);
        let tiles =
            requests.iter().enumerate().map(|(i, r)| Tile { page: i as u32, x: 0, y: 0, size: r.resolution }).collect();
        let pages = (requests.len() as u32).next_power_of_two().min(self.max_pages);
        (tiles, side, pages)
    }

    /// Splits a batch into consecutive chunks that each fit one atlas: at most `max_pages`
    /// (itself at most [`CHUNK_VIEWS`]) views and at most [`CHUNK_PIXELS`] page pixels (a
    /// larger view alone).
    fn chunks(&self, requests: &[ViewRequest<'_>]) -> Vec<std::ops::Range<usize>> {
        let mut chunks = Vec::new();
        let (mut start, mut side) = (0usize, 0u64);
        for (i, request) in requests.iter().enumerate() {
            let wider = side.max(u64::from(request.resolution.next_multiple_of(64)));
            let views = (i + 1 - start) as u64;
            if i > start && (views > u64::from(self.max_pages) || views * wider * wider > CHUNK_PIXELS) {
                chunks.push(start..i);
                start = i;
                side = u64::from(request.resolution.next_multiple_of(64));
            } else {
                side = wider;
            }
        }
        if start < requests.len() {
            chunks.push(start..requests.len());
        }
        chunks
    }

    fn create_atlas(&self, side: u32, pages: u32, full: bool) -> Atlas {
        let texture = |label: &str, format, usage, layers: u32| {
            let texture = self.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d { width: side, height: side, depth_or_array_layers: layers },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            });
            let layers = (0..layers)
                .map(|layer| {
                    texture.create_view(&wgpu::TextureViewDescriptor {
                        dimension: Some(wgpu::TextureViewDimension::D2),
                        base_array_layer: layer,
                        array_layer_count: Some(1),
                        ..Default::default()
                    })
                })
                .collect();
            PagedTexture { texture, layers }
        };
        let target = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC;
        let colour = texture("esrp-render atlas colour", COLOUR_FORMAT, target, pages);
        let depth = texture("esrp-render atlas depth", DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT, 1);
        let extras = full.then(|| {
            [
                texture("esrp-render atlas view depth", DEPTH_OUT_FORMAT, target, pages),
                texture("esrp-render atlas segmentation", SEGMENT_FORMAT, target, pages),
            ]
        });
        let planes = if full { 3 } else { 1 };
        let readback = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("esrp-render readback"),
            size: u64::from(side) * u64::from(side) * 4 * u64::from(pages) * planes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let depth = depth.layers.into_iter().next().unwrap_or_else(|| depth.texture.create_view(&Default::default()));
        let uniforms = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("esrp-render views"),
            size: u64::from(pages) * VIEW_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("esrp-render views"),
            layout: &self.bind_group_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &uniforms,
                    offset: 0,
                    size: NonZeroU64::new(std::mem::size_of::<GpuView>() as u64),
                }),
            }],
        });
        Atlas { side, pages, full, colour, depth, extras, readback, uniforms, bind_group, last_used: 0 }
    }

    /// The runs of `request.scene`'s indices to draw for `request`: all of them, or with
    /// culling on, for an egocentric view, those of the pieces whose bounding spheres are not
    /// wholly outside the view volume (consecutive ones merged into one draw).
    fn index_ranges(&self, request: &ViewRequest<'_>) -> Vec<std::ops::Range<u32>> {
        let scene = request.scene;
        let everything = std::iter::once(0..scene.index_count).collect();
        let Camera::Ego(camera) = request.camera else { return everything };
        if !self.cull {
            return everything;
        }
        let frustum = EgoFrustum::new(&camera);
        let mut ranges: Vec<std::ops::Range<u32>> = Vec::new();
        for part in &scene.parts {
            let centre = match part.slot.checked_sub(1).and_then(|i| request.object_poses.get(i as usize)) {
                None => part.centre,
                Some(pose) => {
                    // As the shader places a movable object's vertices.
                    let (s, c) = pose.yaw.sin_cos();
                    let [x, y, z] = part.centre;
                    [c * x + s * z + pose.x, y, -s * x + c * z + pose.z]
                }
            };
            if frustum.excludes(centre, part.radius) {
                continue;
            }
            let range = part.first..part.first + part.count;
            match ranges.last_mut() {
                Some(last) if last.end == range.start => last.end = range.end,
                _ => ranges.push(range),
            }
        }
        ranges
    }

    /// Number of triangles `request` draws after culling (every triangle of its scene with
    /// culling off, or for a top-down view).
    pub fn triangles_drawn(&self, request: &ViewRequest<'_>) -> usize {
        self.index_ranges(request).iter().map(|r| r.len()).sum::<usize>() / 3
    }

    /// Renders any number and mix of views of any scenes into the pages of one atlas (one
    /// render pass per page), with one submit and one readback per chunk. Outputs are in
    /// request order and bit-identical to rendering each view alone. A batch larger than one
    /// atlas (more than [`CHUNK_VIEWS`] views, more pages than the device's texture array
    /// holds, or more than [`CHUNK_PIXELS`] page pixels) is drawn in consecutive chunks, so
    /// callers never split batches themselves.
    ///
    /// If any view asks for depth or segmentation, the whole batch is drawn with the pipeline
    /// that writes them (a little slower); only the views that asked get them.
    pub fn render_batch(&self, requests: &[ViewRequest<'_>]) -> Result<Vec<ViewOutput>, RenderError> {
        if let Some(reason) = self.lost.lock().ok().and_then(|slot| slot.clone()) {
            return Err(RenderError::DeviceLost { reason });
        }
        if requests.is_empty() {
            return Ok(Vec::new());
        }
        self.validate(requests)?;
        let full = requests.iter().any(|r| r.outputs.any_extra());
        let mut outputs = Vec::with_capacity(requests.len());
        for chunk in self.chunks(requests) {
            outputs.extend(self.render_chunk(&requests[chunk], full)?);
        }
        Ok(outputs)
    }

    /// Renders a validated chunk of a batch with one submit and one readback.
    fn render_chunk(&self, requests: &[ViewRequest<'_>], full: bool) -> Result<Vec<ViewOutput>, RenderError> {
        let (tiles, side, pages) = self.layout(requests);

        let t0 = Instant::now();
        let (taken, now) = {
            let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
            state.batches += 1;
            let taken = state
                .atlases
                .iter()
                .position(|a| a.side == side && a.pages == pages && a.full == full)
                .map(|i| state.atlases.swap_remove(i));
            (taken, state.batches)
        };
        let mut atlas = taken.unwrap_or_else(|| self.create_atlas(side, pages, full));
        let result = self.draw_and_read(&atlas, requests, &tiles, t0);
        atlas.last_used = now;
        let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        state.atlases.push(atlas);
        if state.atlases.len() > CACHED_ATLASES
            && let Some(oldest) = (0..state.atlases.len()).min_by_key(|&i| state.atlases[i].last_used)
        {
            state.atlases.swap_remove(oldest);
        }
        result
    }

    /// Draws `requests` into `atlas` (one page each), submits, waits for that submission and
    /// extracts every view.
    fn draw_and_read(
        &self,
        atlas: &Atlas,
        requests: &[ViewRequest<'_>],
        tiles: &[Tile],
        t0: Instant,
    ) -> Result<Vec<ViewOutput>, RenderError> {
        // Per-view uniforms: camera and the movable objects' poses.
        let mut uniforms = vec![0u8; requests.len() * VIEW_STRIDE as usize];
        for (i, request) in requests.iter().enumerate() {
            let mut view = match request.camera {
                Camera::Ego(camera) => ego_view(&camera),
                Camera::TopDown => top_down_view(&request.scene.frame, request.scene.max_height),
            };
            for (slot, pose) in view.poses[1..].iter_mut().zip(request.object_poses) {
                let (s, c) = pose.yaw.sin_cos();
                // Poses are relative to nothing: f32 keeps millimetres over kilometres.
                *slot = [c as f32, s as f32, pose.x as f32, pose.z as f32];
            }
            let start = i * VIEW_STRIDE as usize;
            uniforms[start..start + std::mem::size_of::<GpuView>()].copy_from_slice(bytemuck::bytes_of(&view));
        }

        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue.write_buffer(&atlas.uniforms, 0, &uniforms);
        let mut encoder =
            self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("esrp-render batch") });
        let used_pages = tiles.iter().map(|t| t.page + 1).max().unwrap_or(1);
        let [r, g, b] = BACKGROUND_COLOUR.map(f64::from);
        let clear_colour = wgpu::Color { r, g, b, a: 1.0 };
        for page in 0..used_pages {
            let attachment = |view, clear| {
                Some(wgpu::RenderPassColorAttachment {
                    view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations { load: wgpu::LoadOp::Clear(clear), store: wgpu::StoreOp::Store },
                })
            };
            let mut attachments = vec![attachment(&atlas.colour.layers[page as usize], clear_colour)];
            if let Some(extras) = &atlas.extras {
                attachments.push(attachment(&extras[0].layers[page as usize], wgpu::Color::TRANSPARENT));
                attachments.push(attachment(&extras[1].layers[page as usize], wgpu::Color::TRANSPARENT));
            }
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("esrp-render page"),
                color_attachments: &attachments,
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &atlas.depth,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Discard }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(if atlas.full { &self.pipeline_full } else { &self.pipeline_rgb });
            for (i, (request, tile)) in requests.iter().zip(tiles).enumerate() {
                let scene = request.scene;
                if tile.page != page || scene.index_count == 0 {
                    continue;
                }
                pass.set_viewport(tile.x as f32, tile.y as f32, tile.size as f32, tile.size as f32, 0.0, 1.0);
                pass.set_scissor_rect(tile.x, tile.y, tile.size, tile.size);
                pass.set_bind_group(0, &atlas.bind_group, &[(i as u64 * VIEW_STRIDE) as u32]);
                pass.set_vertex_buffer(0, scene.vertex_buffer.slice(..));
                pass.set_index_buffer(scene.index_buffer.slice(..), wgpu::IndexFormat::Uint32);
                for range in self.index_ranges(request) {
                    pass.draw_indexed(range, 0, 0..1);
                }
            }
        }
        let copy = |encoder: &mut wgpu::CommandEncoder, texture: &wgpu::Texture, plane: u64| {
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &atlas.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: plane * atlas.plane_bytes(),
                        bytes_per_row: Some(atlas.side * 4),
                        rows_per_image: Some(atlas.side),
                    },
                },
                wgpu::Extent3d { width: atlas.side, height: atlas.side, depth_or_array_layers: used_pages },
            );
        };
        copy(&mut encoder, &atlas.colour.texture, 0);
        if let Some(extras) = &atlas.extras {
            copy(&mut encoder, &extras[0].texture, 1);
            copy(&mut encoder, &extras[1].texture, 2);
        }
        let t1 = Instant::now();
        let submission = self.queue.submit([encoder.finish()]);

        let (sender, receiver) = std::sync::mpsc::channel();
        let planes = if atlas.full { 3 } else { 1 };
        atlas.readback.map_async(wgpu::MapMode::Read, 0..atlas.plane_bytes() * planes, move |result| {
            let _ = sender.send(result);
        });
        // Wait for this submission only: another thread's later batch may still be running.
        let polled = self.device.poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None });
        // Another thread's poll may be the one that runs our map callback: wait for it a
        // little, polling again meanwhile, rather than assuming our poll ran it.
        let mut mapped = false;
        if polled.is_ok() {
            let deadline = Instant::now() + std::time::Duration::from_secs(10);
            loop {
                match receiver.recv_timeout(std::time::Duration::from_millis(1)) {
                    Ok(result) => {
                        mapped = result.is_ok();
                        break;
                    }
                    Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) if Instant::now() < deadline => {
                        let _ = self.device.poll(wgpu::PollType::Poll);
                    }
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => break,
                }
            }
        }
        let failure = if let Some(error) = pollster::block_on(scope.pop()) {
            Some(RenderError::Gpu { reason: error.to_string() })
        } else if let Some(reason) = self.lost.lock().ok().and_then(|slot| slot.clone()) {
            Some(RenderError::DeviceLost { reason })
        } else if let Err(e) = polled {
            Some(RenderError::Readback { reason: e.to_string() })
        } else if !mapped {
            Some(RenderError::Readback { reason: "the readback buffer could not be mapped".into() })
        } else {
            None
        };
        if let Some(error) = failure {
            if mapped {
                atlas.readback.unmap();
            }
            return Err(error);
        }
        let t2 = Instant::now();
        let outputs = {
            let mapped =
                atlas.readback.get_mapped_range(..).map_err(|e| RenderError::Readback { reason: format!("{e:?}") })?;
            let planes = Planes {
                bytes: &mapped,
                plane_bytes: atlas.plane_bytes() as usize,
                page_bytes: atlas.page_bytes() as usize,
                row_bytes: atlas.side as usize * 4,
                full: atlas.full,
            };
            extract_all(&planes, requests, tiles)
        };
        atlas.readback.unmap();
        let outputs = outputs?;
        log::trace!(
            "esrp-render: {} views, {} pages of {}x{}: encode {:?}, device {:?}, extract {:?}",
            requests.len(),
            atlas.pages,
            atlas.side,
            atlas.side,
            t1 - t0,
            t2 - t1,
            t2.elapsed()
        );
        Ok(outputs)
    }
}

/// The mapped readback buffer: one plane per output texture, rows of `row_bytes`.
struct Planes<'a> {
    bytes: &'a [u8],
    plane_bytes: usize,
    page_bytes: usize,
    row_bytes: usize,
    full: bool,
}

impl Planes<'_> {
    /// The `row`-th row of `tile` in `plane`, 4 bytes per pixel.
    fn row(&self, plane: usize, tile: &Tile, row: usize) -> &[u8] {
        let start = plane * self.plane_bytes
            + tile.page as usize * self.page_bytes
            + (tile.y as usize + row) * self.row_bytes
            + tile.x as usize * 4;
        &self.bytes[start..start + tile.size as usize * 4]
    }

    fn words(&self, plane: usize, tile: &Tile) -> Vec<u32> {
        let n = tile.size as usize;
        let mut out = vec![0u32; n * n];
        for (row, dst) in out.chunks_exact_mut(n).enumerate() {
            for (d, s) in dst.iter_mut().zip(self.row(plane, tile, row).chunks_exact(4)) {
                *d = u32::from_le_bytes([s[0], s[1], s[2], s[3]]);
            }
        }
        out
    }

    fn extract(&self, request: &ViewRequest<'_>, tile: &Tile) -> ViewOutput {
        let n = tile.size as usize;
        let mut rgb = vec![0u8; n * n * 3];
        for (row, dst) in rgb.chunks_exact_mut(n * 3).enumerate() {
            rgba_to_rgb(self.row(0, tile, row), dst);
        }
        let depth = (request.outputs.depth && self.full).then(|| {
            self.words(1, tile)
                .into_iter()
                .map(|bits| {
                    let d = f32::from_bits(bits);
                    if d > 0.0 { d } else { f32::INFINITY }
                })
                .collect()
        });
        let segmentation = (request.outputs.segmentation && self.full).then(|| self.words(2, tile));
        ViewOutput { resolution: tile.size, rgb: Bytes::from(rgb), depth, segmentation }
    }
}

/// Drops the alpha byte of each pixel: `src` is RGBA, `dst` RGB, same pixel count. Four
/// pixels at a time as three little-endian words, which compiles to a tight loop.
fn rgba_to_rgb(src: &[u8], dst: &mut [u8]) {
    let mut src_quads = src.chunks_exact(16);
    let mut dst_quads = dst.chunks_exact_mut(12);
    for (s, d) in (&mut src_quads).zip(&mut dst_quads) {
        let p = |i: usize| u32::from_le_bytes([s[4 * i], s[4 * i + 1], s[4 * i + 2], s[4 * i + 3]]);
        let (p0, p1, p2, p3) = (p(0), p(1), p(2), p(3));
        d[0..4].copy_from_slice(&((p0 & 0x00ff_ffff) | (p1 << 24)).to_le_bytes());
        d[4..8].copy_from_slice(&(((p1 >> 8) & 0xffff) | (p2 << 16)).to_le_bytes());
        d[8..12].copy_from_slice(&(((p2 >> 16) & 0xff) | (p3 << 8)).to_le_bytes());
    }
    for (s, d) in src_quads.remainder().chunks_exact(4).zip(dst_quads.into_remainder().chunks_exact_mut(3)) {
        d.copy_from_slice(&s[..3]);
    }
}

/// Extracts every view's images from the atlas; large batches use several threads, since the
/// device is idle by then.
fn extract_all(
    planes: &Planes<'_>,
    requests: &[ViewRequest<'_>],
    tiles: &[Tile],
) -> Result<Vec<ViewOutput>, RenderError> {
    const PIXELS_PER_THREAD: u64 = 1 << 18;
    let pixels: u64 = tiles.iter().map(|t| u64::from(t.size).pow(2)).sum();
    // available_parallelism reads cgroup files on every call: ask once.
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    let threads = (*CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))).min(8);
    let threads = threads.min((pixels / PIXELS_PER_THREAD) as usize).max(1);
    if threads == 1 {
        return Ok(requests.iter().zip(tiles).map(|(r, t)| planes.extract(r, t)).collect());
    }
    let chunk = requests.len().div_ceil(threads);
    std::thread::scope(|scope| {
        // The calling thread takes the first chunk; helpers take the rest.
        let workers: Vec<_> = requests
            .chunks(chunk)
            .zip(tiles.chunks(chunk))
            .skip(1)
            .map(|(rs, ts)| {
                scope.spawn(move || rs.iter().zip(ts).map(|(r, t)| planes.extract(r, t)).collect::<Vec<_>>())
            })
            .collect();
        let first = requests.len().min(chunk);
        let mut out: Vec<ViewOutput> =
            requests[..first].iter().zip(&tiles[..first]).map(|(r, t)| planes.extract(r, t)).collect();
        for worker in workers {
            out.extend(
                worker.join().map_err(|_| RenderError::Readback { reason: "an extraction thread panicked".into() })?,
            );
        }
        Ok(out)
    })
}

/// The renderer and scene handles are shared across threads (see the module docs).
const _: () = {
    const fn check<T: Send + Sync>() {}
    check::<Renderer>();
    check::<SceneHandle>();
};

#[cfg(test)]
mod tests {
    #[test]
    fn rgba_to_rgb_drops_alpha_for_every_length() {
        for pixels in 0..11usize {
            let src: Vec<u8> = (0..pixels * 4).map(|i| if i % 4 == 3 { 255 } else { i as u8 }).collect();
            let mut dst = vec![0u8; pixels * 3];
            super::rgba_to_rgb(&src, &mut dst);
            let expected: Vec<u8> = src.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
            assert_eq!(dst, expected);
        }
    }

    #[test]
    fn backend_names_round_trip_and_unknown_names_are_errors() {
        use super::BackendPreference;
        for name in BackendPreference::NAMES {
            let backend: BackendPreference = name.parse().unwrap();
            assert_eq!(backend.to_string(), name);
        }
        assert_eq!("OpenGL".parse::<BackendPreference>().unwrap(), BackendPreference::Gl);
        let error = "metal".parse::<BackendPreference>().unwrap_err().to_string();
        assert!(error.contains("\"metal\"") && error.contains("auto, vulkan or gl"), "{error}");
    }
}
