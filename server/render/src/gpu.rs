//! `#[repr(C)]` Pod structs that mirror `shader.wgsl` (`VertexIn` and `View`): change both
//! together.

use bytemuck::{Pod, Zeroable};

/// The WGSL source of the renderer's graphics pipelines.
pub(crate) const SHADER_SOURCE: &str = include_str!("shader.wgsl");

/// Where a view's target (`View.tile` in `raster.wgsl`: its page, resolution, triangle count
/// and page side, four u32) lies in its uniforms, after [`GpuView`].
pub(crate) const VIEW_TARGET_OFFSET: usize = 240;

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
}

const _: () = assert!(std::mem::size_of::<GpuView>() == VIEW_TARGET_OFFSET);
const _: () = assert!(VIEW_TARGET_OFFSET as u64 + 16 <= VIEW_STRIDE);
const _: () = assert!(std::mem::size_of::<GpuVertex>() == 36);
