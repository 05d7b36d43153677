//! The compute rasteriser ([`Rasterizer::Compute`](super::Rasterizer::Compute)): its pipelines
//! and bind group layouts, a scene's bind group, and the encoding of a chunk's views into an
//! atlas's storage buffer (`raster.wgsl`).

use std::num::NonZeroU64;

use crate::gpu::{RASTER_SOURCE, VIEW_STRIDE};
use crate::mesh::BACKGROUND_COLOUR;

use super::atlas::Tile;
use super::requests::ViewRequest;

/// The compute rasteriser's source, with `BACKGROUND`, the colour of a pixel no triangle covers,
/// stored as the graphics pipeline stores its clear colour in an Rgba8Unorm target.
fn raster_source() -> String {
    let [r, g, b] = BACKGROUND_COLOUR.map(|c| (c.clamp(0.0, 1.0) * 255.0 + 0.5).floor() as u32);
    let packed = r | (g << 8) | (b << 16) | (255 << 24);
    format!("const BACKGROUND: u32 = {packed}u;\n{RASTER_SOURCE}")
}

/// Pixels on a side of the tile one workgroup draws (`TILE` in `raster.wgsl`).
const TILE: u32 = 32;

/// The compute rasteriser's two pipelines (`rgb`: the colour plane; `full`: colour, view depth
/// and segmentation) and their bind group layouts: group 0 a view's uniforms (dynamic offset)
/// and the atlas's planes, group 1 a scene's vertices and indices.
pub(crate) struct ComputeRaster {
    pub(super) views_layout: wgpu::BindGroupLayout,
    pub(super) scene_layout: wgpu::BindGroupLayout,
    rgb: wgpu::ComputePipeline,
    full: wgpu::ComputePipeline,
}

impl ComputeRaster {
    /// Builds them on `device` (its validation errors are the caller's error scope's).
    pub(super) fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("esrp-render raster"),
            source: wgpu::ShaderSource::Wgsl(raster_source().into()),
        });
        let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: NonZeroU64::new(4),
            },
            count: None,
        };
        let views_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("esrp-render raster views"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: true,
                        min_binding_size: NonZeroU64::new(VIEW_STRIDE),
                    },
                    count: None,
                },
                storage(1, false),
            ],
        });
        let scene_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("esrp-render raster scene"),
            entries: &[storage(0, true), storage(1, true)],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("esrp-render raster"),
            bind_group_layouts: &[Some(&views_layout), Some(&scene_layout)],
            immediate_size: 0,
        });
        let pipeline = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        Self { rgb: pipeline("raster_rgb"), full: pipeline("raster_full"), views_layout, scene_layout }
    }

    /// A scene's group 1: its vertex and index buffers (made with `STORAGE` usage).
    pub(super) fn scene_bind_group(
        &self,
        device: &wgpu::Device,
        vertices: &wgpu::Buffer,
        indices: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("esrp-render raster scene"),
            layout: &self.scene_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: vertices.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: indices.as_entire_binding() },
            ],
        })
    }

    /// Encodes one compute pass that draws every view of `requests` into its page of an atlas
    /// whose pages' buffers and group 0 are `pages` (one dispatch per view: a workgroup per
    /// 32×32 tile of it). Every pixel of a view is written, so the planes need no clearing. With
    /// `timestamps`, the device writes its clock into queries 0 and 1 at the pass's start and end.
    pub(super) fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pages: &[(wgpu::Buffer, wgpu::BindGroup)],
        full: bool,
        requests: &[ViewRequest<'_>],
        tiles: &[Tile],
        timestamps: Option<&wgpu::QuerySet>,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("esrp-render raster"),
            timestamp_writes: timestamps.map(|query_set| wgpu::ComputePassTimestampWrites {
                query_set,
                beginning_of_pass_write_index: Some(0),
                end_of_pass_write_index: Some(1),
            }),
        });
        pass.set_pipeline(if full { &self.full } else { &self.rgb });
        for (i, (request, tile)) in requests.iter().zip(tiles).enumerate() {
            let (Some(scene), Some((_, views))) = (&request.scene.raster_bind_group, pages.get(tile.page as usize))
            else {
                continue;
            };
            pass.set_bind_group(0, views, &[(i as u64 * VIEW_STRIDE) as u32]);
            pass.set_bind_group(1, scene, &[]);
            let groups = tile.size.div_ceil(TILE);
            pass.dispatch_workgroups(groups, groups, 1);
        }
    }
}
