//! The texture formats of an atlas's planes and of the pipelines that draw into them.

pub(super) const COLOUR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
pub(super) const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// View depth as the bits of an `f32` (R32Float is not renderable on OpenGL ES).
pub(super) const DEPTH_OUT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
pub(super) const SEGMENT_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
