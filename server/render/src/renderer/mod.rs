//! The long-lived [`Renderer`]: device, queue, pipelines, scene uploads and batched rendering
//! into an atlas. This module creates the renderer and takes its uploads and batches; the struct
//! and its fields are in `device`, which this module and `draw` build on. `backend` chooses the
//! graphics backend and adapter, `formats` and `limits` hold the texture formats and the sizes
//! (default resolution, chunk limits, pose slots), `requests` what the renderer is asked and
//! answers and the check of a batch, `atlas` the textures a batch draws into, their pool and how
//! a batch is laid out and chunked, `draw` the pieces a view draws and one chunk's encoder,
//! submit and readback, `readback` the images cut out of the read-back planes, and `clock` the
//! timestamps that time the device's drawing.
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

use esrp_core::CompiledScene;
use wgpu::util::DeviceExt;

use crate::camera::TopDownFrame;
use crate::error::RenderError;
use crate::gpu::{GpuVertex, GpuView, SHADER_SOURCE};
use crate::mesh::build_scene_mesh;

mod atlas;
mod backend;
mod clock;
mod compute;
mod device;
mod draw;
mod formats;
mod limits;
mod readback;
mod requests;

use atlas::{BatchState, chunks};
use backend::request_adapter;
pub use backend::{
    BackendPreference, DepthBuffers, Rasterizer, RendererConfig, Timestamps, UnknownBackend, UnknownDepthBuffers,
    UnknownRasterizer, UnknownTimestamps,
};
pub use device::Renderer;
pub use draw::RenderTimings;
use formats::{COLOUR_FORMAT, DEPTH_FORMAT, DEPTH_OUT_FORMAT, SEGMENT_FORMAT};
pub use limits::{CHUNK_PIXELS, CHUNK_VIEWS, DEFAULT_RESOLUTION, MAX_MOVABLE_OBJECTS};
#[cfg(test)]
use readback::rgba_to_rgb;
use requests::validate;
pub use requests::{Outputs, SceneHandle, ViewOutput, ViewRequest};

/// The adapter `backends` asks for: with [`BackendPreference::Auto`], a GPU through Vulkan
/// first; without one, both APIs reach Mesa's CPU rasteriser, and OpenGL (llvmpipe) draws in the
/// calling thread where Vulkan (lavapipe) hands every submission to a queue thread, and measured
/// faster end to end (docs/performance.md), so it comes before lavapipe.
fn choose_adapter(backends: BackendPreference, power: wgpu::PowerPreference) -> Result<wgpu::Adapter, RenderError> {
    let (adapter, tried) = match backends {
        BackendPreference::Auto => {
            let adapter = match request_adapter(wgpu::Backends::VULKAN, power) {
                Some(vulkan) if vulkan.get_info().device_type != wgpu::DeviceType::Cpu => Some(vulkan),
                vulkan => request_adapter(wgpu::Backends::GL, power).or(vulkan),
            };
            (adapter, "vulkan, gl")
        }
        BackendPreference::Vulkan => (request_adapter(wgpu::Backends::VULKAN, power), "vulkan"),
        BackendPreference::Gl => (request_adapter(wgpu::Backends::GL, power), "gl"),
    };
    adapter.ok_or_else(|| RenderError::NoAdapter { tried: tried.to_owned() })
}

/// The shader's two pipelines and the per-view uniform layout they share: `rgb` draws the colour
/// plane alone, `full` the colour, depth and segmentation planes.
struct Pipelines {
    bind_group_layout: wgpu::BindGroupLayout,
    rgb: wgpu::RenderPipeline,
    full: wgpu::RenderPipeline,
}

impl Pipelines {
    /// Builds them on `device` (its validation errors are the caller's error scope's).
    fn new(device: &wgpu::Device) -> Self {
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
        let rgb = pipeline("vs_rgb", "fs_rgb", &[target(COLOUR_FORMAT)]);
        let full =
            pipeline("vs_full", "fs_full", &[target(COLOUR_FORMAT), target(DEPTH_OUT_FORMAT), target(SEGMENT_FORMAT)]);
        Self { bind_group_layout, rgb, full }
    }
}

static NEXT_RENDERER_ID: AtomicU64 = AtomicU64::new(1);

impl Renderer {
    /// Creates the device, the pipelines and the uniform buffer, and logs the adapter.
    ///
    /// Fails with [`RenderError::NoAdapter`] (never panics) when no adapter exists.
    pub fn new(config: RendererConfig) -> Result<Self, RenderError> {
        let adapter = choose_adapter(config.backends, config.power_preference)?;
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
        let timestamps = config.timestamps.wanted(adapter_info.device_type)
            && adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("esrp-render"),
            required_features: if timestamps { wgpu::Features::TIMESTAMP_QUERY } else { wgpu::Features::empty() },
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| RenderError::RequestDevice {
            adapter: adapter_info.name.clone(),
            reason: format!("{e}{}", nvidia_gl_hint(&adapter_info)),
        })?;

        let lost = Arc::new(Mutex::new(None));
        let lost_flag = Arc::clone(&lost);
        let hint = nvidia_gl_hint(&adapter_info);
        device.set_device_lost_callback(move |reason, message| {
            if let Ok(mut slot) = lost_flag.lock() {
                *slot = Some(format!("{reason:?}: {message}{hint}"));
            }
        });

        // Errors are returned from the operations that cause them (error scopes); anything else
        // is logged rather than aborting the process, as wgpu does by default.
        device.on_uncaptured_error(Arc::new(|error| log::error!("esrp-render: uncaptured wgpu error: {error}")));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let Pipelines { bind_group_layout, rgb: pipeline_rgb, full: pipeline_full } = Pipelines::new(&device);
        let raster = match config.rasterizer {
            Rasterizer::Pipeline => None,
            Rasterizer::Compute => {
                let missing = compute_raster_missing(&adapter, &limits);
                if let Some(missing) = missing {
                    return Err(RenderError::RequestDevice {
                        adapter: adapter_info.name.clone(),
                        reason: format!("the compute rasterizer needs {missing}: use the pipeline rasterizer"),
                    });
                }
                Some(compute::ComputeRaster::new(&device))
            }
        };
        if let Some(error) = pollster::block_on(scope.pop()) {
            return Err(RenderError::RequestDevice {
                adapter: adapter_info.name.clone(),
                reason: format!("the adapter cannot build the pipelines: {error}"),
            });
        }

        // A device whose timestamps fail their check is not timed: a batch's error would fail
        // its views.
        let timestamps = timestamps
            && clock::check_timestamps(&device, &queue)
                .map_err(|reason| {
                    log::warn!(
                        "esrp-render: {}: not timing the device: its timestamps failed a check: {reason}",
                        adapter_info.name
                    )
                })
                .is_ok();
        let timestamp_period = timestamps.then(|| queue.get_timestamp_period());
        let max_side = config.max_atlas_size.min(limits.max_texture_dimension_2d).max(64);
        let max_atlas = 1u32 << (31 - max_side.leading_zeros());
        Ok(Self {
            id: NEXT_RENDERER_ID.fetch_add(1, Ordering::Relaxed),
            adapter_info,
            device,
            queue,
            pipeline_rgb,
            pipeline_full,
            bind_group_layout,
            raster,
            max_atlas,
            max_pages: limits.max_texture_array_layers.clamp(1, CHUNK_VIEWS as u32),
            cull: config.cull,
            timestamp_period,
            depth_buffers: config.depth_buffers,
            lost,
            state: Mutex::new(BatchState::new()),
        })
    }

    /// The adapter in use (name, backend, driver).
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.adapter_info
    }

    /// What draws this renderer's triangles.
    pub fn rasterizer(&self) -> Rasterizer {
        if self.raster.is_some() { Rasterizer::Compute } else { Rasterizer::Pipeline }
    }

    /// Whether the renderer times each batch's drawing on the device's clock
    /// ([`RendererConfig::timestamps`] asks for it, and the adapter has timestamp queries).
    pub fn times_device(&self) -> bool {
        self.timestamp_period.is_some()
    }

    /// Whether the adapter is a CPU rasteriser (lavapipe, llvmpipe).
    pub fn is_software(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::Cpu
    }

    /// How many atlases (the textures and buffers a batch draws into, pooled between batches)
    /// this renderer has made so far: a figure that keeps rising under a steady load means
    /// batches keep allocating on the device.
    pub fn atlases_created(&self) -> u64 {
        self.state.lock().map_or_else(|poisoned| poisoned.into_inner().created, |state| state.created)
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
        // The compute rasteriser reads them as storage buffers.
        let storage = if self.raster.is_some() { wgpu::BufferUsages::STORAGE } else { wgpu::BufferUsages::empty() };
        let vertex_buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("esrp-render scene vertices"),
            contents: bytemuck::cast_slice(&vertices),
            usage: wgpu::BufferUsages::VERTEX | storage,
        });
        let index_buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("esrp-render scene indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::INDEX | storage,
        });
        let raster_bind_group =
            self.raster.as_ref().map(|raster| raster.scene_bind_group(&self.device, &vertex_buffer, &index_buffer));
        Ok(Arc::new(SceneHandle {
            renderer_id: self.id,
            scene_id: scene.scene().id.clone(),
            vertex_buffer,
            index_buffer,
            raster_bind_group,
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
        self.render_batch_timed(requests).map(|(outputs, _)| outputs)
    }

    /// [`Renderer::render_batch`], and where its time went on the calling thread
    /// ([`RenderTimings`]: encoding, submitting, the device and extraction, and the device's
    /// drawing by its own clock where it is timed), summed over its chunks.
    pub fn render_batch_timed(
        &self,
        requests: &[ViewRequest<'_>],
    ) -> Result<(Vec<ViewOutput>, RenderTimings), RenderError> {
        let mut timings = RenderTimings::default();
        let full = self.check_batch(requests)?;
        if requests.is_empty() {
            return Ok((Vec::new(), timings));
        }
        let mut outputs = Vec::with_capacity(requests.len());
        for chunk in chunks(requests, self.max_pages) {
            outputs.extend(self.render_chunk(&requests[chunk], full, &mut timings)?);
        }
        Ok((outputs, timings))
    }

    /// Why the device was lost, if it was.
    pub(super) fn lost_reason(&self) -> Option<String> {
        self.lost.lock().ok().and_then(|slot| slot.clone())
    }

    /// Checks a batch before it is drawn: the device is not lost and every request is valid
    /// ([`validate`]). Returns whether the batch is drawn with the extra planes (any view asks
    /// for depth or segmentation).
    fn check_batch(&self, requests: &[ViewRequest<'_>]) -> Result<bool, RenderError> {
        if let Some(reason) = self.lost_reason() {
            return Err(RenderError::DeviceLost { reason });
        }
        validate(requests, self.id, self.max_atlas)?;
        Ok(requests.iter().any(|r| r.outputs.any_extra()))
    }

    /// Starts rendering `requests` as [`Renderer::render_batch`] does, and returns once the
    /// batch is submitted, without waiting for the device: the caller encodes and submits the
    /// next batch while this one is drawn, and hands the [`SubmittedBatch`] to
    /// [`Renderer::finish_batch`] (on any thread) for its images. Every chunk of the batch is
    /// submitted at once and holds an atlas until it is finished, so keep batches within
    /// [`CHUNK_VIEWS`] views. Errors of the requests and of the encoding are returned here.
    pub fn submit_batch(&self, requests: &[ViewRequest<'_>]) -> Result<SubmittedBatch, RenderError> {
        let mut timings = RenderTimings::default();
        let full = self.check_batch(requests)?;
        let mut submitted = Vec::new();
        for chunk in chunks(requests, self.max_pages) {
            submitted.push(self.submit_chunk(&requests[chunk], full, &mut timings)?);
        }
        Ok(SubmittedBatch { renderer_id: self.id, chunks: submitted, timings })
    }

    /// Waits for a batch of [`Renderer::submit_batch`] and returns its views in request order
    /// (bit-identical to [`Renderer::render_batch`]'s), with where its time went: the encoding
    /// and the submit, then the device (from the submit until the images could be read, the
    /// batches submitted before it included, and its drawing by its own clock where it is
    /// timed) and the extraction.
    pub fn finish_batch(&self, batch: SubmittedBatch) -> Result<(Vec<ViewOutput>, RenderTimings), RenderError> {
        if batch.renderer_id != self.id {
            return Err(RenderError::ForeignBatch);
        }
        let SubmittedBatch { chunks, mut timings, .. } = batch;
        let mut outputs = Vec::new();
        for chunk in chunks {
            outputs.extend(self.finish_chunk(chunk, &mut timings)?);
        }
        Ok((outputs, timings))
    }
}

/// A batch submitted to the device by [`Renderer::submit_batch`] and not yet read back; give it
/// to [`Renderer::finish_batch`] of the same renderer. Dropping it abandons its images.
pub struct SubmittedBatch {
    renderer_id: u64,
    chunks: Vec<draw::SubmittedChunk>,
    /// The encoding's time so far.
    timings: RenderTimings,
}

impl std::fmt::Debug for SubmittedBatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SubmittedBatch").field("submissions", &self.chunks.len()).finish_non_exhaustive()
    }
}

/// What the adapter lacks for the compute rasteriser, if anything: compute shaders, three storage
/// buffers in a compute shader, or the workgroup memory and size of `raster.wgsl`.
fn compute_raster_missing(adapter: &wgpu::Adapter, limits: &wgpu::Limits) -> Option<&'static str> {
    if !adapter.get_downlevel_capabilities().flags.contains(wgpu::DownlevelFlags::COMPUTE_SHADERS) {
        Some("compute shaders")
    } else if limits.max_storage_buffers_per_shader_stage < 3 {
        Some("three storage buffers in a compute shader")
    } else if limits.max_compute_workgroup_storage_size < 16384 || limits.max_compute_invocations_per_workgroup < 256 {
        Some("workgroups of 256 invocations and 16 KiB")
    } else {
        None
    }
}

/// What to say after a device error of OpenGL on an NVIDIA GPU: it failed there ("Parent device
/// is lost" on a lent H100), and Vulkan, which `auto` picks on a GPU, is the path. Empty for any
/// other adapter.
fn nvidia_gl_hint(info: &wgpu::AdapterInfo) -> &'static str {
    gl_hint(info.backend, info.vendor, &info.name)
}

/// [`nvidia_gl_hint`] of an adapter's backend, PCI vendor and name.
fn gl_hint(backend: wgpu::Backend, vendor: u32, name: &str) -> &'static str {
    const NVIDIA: u32 = 0x10de;
    let nvidia = vendor == NVIDIA || name.to_ascii_lowercase().contains("nvidia");
    if backend == wgpu::Backend::Gl && nvidia {
        "; OpenGL on NVIDIA GPUs is known to fail this way: use --render-backend vulkan (what auto picks on a GPU)"
    } else {
        ""
    }
}

/// The renderer and scene handles are shared across threads (see the module docs).
const _: () = {
    const fn check<T: Send + Sync>() {}
    check::<Renderer>();
    check::<SceneHandle>();
    // A submitted batch is finished on another thread than the one that submitted it.
    const fn send<T: Send>() {}
    send::<SubmittedBatch>();
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
    fn opengl_on_nvidia_says_vulkan_is_the_path() {
        use wgpu::Backend::{Gl, Vulkan};
        let info = super::gl_hint;
        assert!(info(Gl, 0x10de, "H100").contains("--render-backend vulkan"));
        assert!(!info(Gl, 0, "NVIDIA H100 80GB HBM3/PCIe/SSE2").is_empty());
        assert!(info(Vulkan, 0x10de, "NVIDIA H100").is_empty());
        assert!(info(Gl, 0x1002, "llvmpipe").is_empty());
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
