//! The [`Renderer`] struct: what it holds on the device and between batches (the pool of
//! atlases). Its methods are implemented where the work is: creation, uploads and batches in the
//! parent module, drawing a chunk in `draw`.

use std::sync::{Arc, Mutex};

use super::atlas::BatchState;

/// The renderer: one per process, long-lived. See [the `renderer` module](crate::renderer#concurrency)
/// for its concurrency.
pub struct Renderer {
    pub(super) id: u64,
    pub(super) adapter_info: wgpu::AdapterInfo,
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
    pub(super) pipeline_rgb: wgpu::RenderPipeline,
    pub(super) pipeline_full: wgpu::RenderPipeline,
    pub(super) bind_group_layout: wgpu::BindGroupLayout,
    /// The compute rasteriser, when it is what draws ([`super::Rasterizer::Compute`]).
    pub(super) raster: Option<super::compute::ComputeRaster>,
    pub(super) max_atlas: u32,
    pub(super) max_pages: u32,
    pub(super) cull: bool,
    /// The nanoseconds of one tick of the device's timestamps, when it times its drawing
    /// ([`super::RendererConfig::timestamps`] on and the adapter able to).
    pub(super) timestamp_period: Option<f32>,
    /// The depth buffers of the graphics pipeline's passes ([`super::RendererConfig::depth_buffers`]).
    pub(super) depth_buffers: super::DepthBuffers,
    pub(super) lost: Arc<Mutex<Option<String>>>,
    pub(super) state: Mutex<BatchState>,
}

impl Renderer {
    /// What this renderer's atlases are made with.
    pub(super) fn atlas_settings(&self) -> super::atlas::AtlasSettings {
        super::atlas::AtlasSettings { timestamps: self.timestamp_period.is_some(), depth: self.depth_buffers }
    }
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("adapter", &self.adapter_info.name)
            .field("backend", &self.adapter_info.backend)
            .finish()
    }
}
