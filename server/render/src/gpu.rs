//! `#[repr(C)]` Pod structs that mirror the shaders (`VertexIn` in `shader.wgsl`, the vertex
//! words `raster.wgsl` reads, and `View` in `view.wgsl`): change them together; and the shaders'
//! sources.

use bytemuck::{Pod, Zeroable};

/// The WGSL source of the renderer's graphics pipelines: the view's uniforms, placement and
/// lighting (`view.wgsl`), then the vertex and fragment shaders.
pub(crate) const SHADER_SOURCE: &str = concat!(include_str!("view.wgsl"), include_str!("shader.wgsl"));

/// The WGSL source of the compute rasteriser: `view.wgsl`, as the graphics pipelines have it,
/// then the rasteriser, which needs its `BACKGROUND` put before (`renderer::compute`).
pub(crate) const RASTER_SOURCE: &str = concat!(include_str!("view.wgsl"), include_str!("raster.wgsl"));

/// Number of pose slots in [`GpuView::poses`] (`MAX_POSE_SLOTS` in the shader): slot 0 for
/// static geometry, slots `1..` for movable objects.
pub(crate) const MAX_POSE_SLOTS: usize = 10;

/// Stride of one view's uniforms in the uniform buffer; the dynamic-offset alignment that every
/// adapter supports.
pub(crate) const VIEW_STRIDE: u64 = 256;

/// One vertex (WGSL `VertexIn`): position in its slot's frame, pose slot, flat normal, colour
/// as RGBA8 and segmentation id.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct GpuVertex {
    pub position: [f32; 3],
    pub slot: u32,
    pub normal: [f32; 3],
    pub colour: u32,
    pub segment: u32,
}

impl GpuVertex {
    pub(crate) const ATTRIBUTES: [wgpu::VertexAttribute; 5] =
        wgpu::vertex_attr_array![0 => Float32x3, 1 => Uint32, 2 => Float32x3, 3 => Uint32, 4 => Uint32];

    pub(crate) fn layout() -> wgpu::VertexBufferLayout<'static> {
        wgpu::VertexBufferLayout {
            array_stride: std::mem::size_of::<GpuVertex>() as u64,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &Self::ATTRIBUTES,
        }
    }
}

/// One view's uniforms (WGSL `View`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct GpuView {
    pub eye: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub forward: [f32; 4],
    pub depth_map: [f32; 4],
    pub poses: [[f32; 4]; MAX_POSE_SLOTS],
    /// The compute rasteriser's target: the view's page, its resolution, its scene's triangle
    /// count and the atlas's page side (unread by the graphics pipelines).
    pub tile: [u32; 4],
}

const _: () = assert!(std::mem::size_of::<GpuView>() as u64 <= VIEW_STRIDE);
const _: () = assert!(std::mem::size_of::<GpuVertex>() == 36);
