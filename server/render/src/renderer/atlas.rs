//! The atlas a batch renders into (textures of pages, one per view, the uniforms and the
//! readback buffer), the pool it is taken from, and how a batch is laid out and chunked.

use std::num::NonZeroU64;

use crate::gpu::{GpuView, VIEW_STRIDE};

use super::backend::DepthBuffers;
use super::clock::{StampQueries, TIMESTAMP_BYTES};
use super::formats::{COLOUR_FORMAT, DEPTH_FORMAT, DEPTH_OUT_FORMAT, SEGMENT_FORMAT};
use super::limits::{CACHED_ATLASES, CHUNK_PIXELS};
use super::requests::ViewRequest;

/// Where one view lies in the atlas.
#[derive(Clone, Copy, Debug)]
pub(super) struct Tile {
    pub(super) page: u32,
    pub(super) x: u32,
    pub(super) y: u32,
    pub(super) size: u32,
}

/// A texture array (one layer per page) and a view of each layer.
pub(super) struct PagedTexture {
    pub(super) texture: wgpu::Texture,
    pub(super) layers: Vec<wgpu::TextureView>,
}

/// What a batch draws into: textures for the graphics pipeline, or a storage buffer for the
/// compute rasteriser.
pub(super) enum Targets {
    /// The colour plane's texture array, the depth buffer (one page that every pass clears in
    /// turn, or a layer per page: [`DepthBuffers`]), and the view depth (as f32 bits) and
    /// segmentation texture arrays when `full`.
    Textures { colour: PagedTexture, depth: PagedTexture, extras: Option<Box<[PagedTexture; 2]>> },
    /// One storage buffer per page (its planes one after the other, as the readback buffer
    /// holds a page's), written by the compute rasteriser, each with its bind group (with the
    /// uniforms): `raster.wgsl`'s group 0. A buffer per page, so that the views' dispatches
    /// write different buffers and the device may run them at once (one buffer written by
    /// every dispatch would put a barrier between each two).
    Buffers { pages: Vec<(wgpu::Buffer, wgpu::BindGroup)> },
}

/// Targets and readback buffer of one atlas shape: `pages` square pages of `side` pixels.
///
/// Pages rather than one big texture: lavapipe's cost of a render pass grows with the area of
/// its target, so views go into small pages, one render pass each, all in one submit, one copy
/// and one map.
pub(super) struct Atlas {
    pub(super) side: u32,
    pub(super) pages: u32,
    pub(super) full: bool,
    pub(super) targets: Targets,
    pub(super) readback: wgpu::Buffer,
    /// Per-view uniforms (one `VIEW_STRIDE` slot per page) and their bind group for the
    /// graphics pipeline.
    pub(super) uniforms: wgpu::Buffer,
    pub(super) bind_group: wgpu::BindGroup,
    /// Where the device writes when it starts and ends drawing a batch, with a renderer that
    /// times the device ([`super::RendererConfig::timestamps`]).
    pub(super) timestamps: Option<StampQueries>,
    pub(super) last_used: u64,
}

impl Atlas {
    /// Creates the targets, readback buffer and uniforms of `pages` pages of `side` pixels, with
    /// the view depth and segmentation planes when `full`, and binds the uniforms with
    /// `bind_group_layout`; with `compute` (the compute rasteriser's group 0 layout), the targets
    /// are a storage buffer bound with it. With `settings.timestamps`, the atlas has its
    /// timestamp queries, and its readback buffer room for them behind its last page.
    pub(super) fn new(
        device: &wgpu::Device,
        bind_group_layout: &wgpu::BindGroupLayout,
        compute: Option<&wgpu::BindGroupLayout>,
        (side, pages): (u32, u32),
        full: bool,
        settings: AtlasSettings,
    ) -> Self {
        let timestamps = settings.timestamps;
        let planes = if full { 3 } else { 1 };
        let bytes = u64::from(side) * u64::from(side) * 4 * u64::from(pages) * planes;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("esrp-render readback"),
            size: bytes + if timestamps { TIMESTAMP_BYTES } else { 0 },
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("esrp-render views"),
            size: u64::from(pages) * VIEW_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("esrp-render views"),
            layout: bind_group_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &uniforms,
                    offset: 0,
                    size: NonZeroU64::new(std::mem::size_of::<GpuView>() as u64),
                }),
            }],
        });
        let targets = match compute {
            Some(layout) => {
                let page = |_| {
                    let planes = device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("esrp-render atlas page"),
                        size: bytes / u64::from(pages),
                        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                        mapped_at_creation: false,
                    });
                    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("esrp-render raster view"),
                        layout,
                        entries: &[
                            wgpu::BindGroupEntry {
                                binding: 0,
                                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                    buffer: &uniforms,
                                    offset: 0,
                                    size: NonZeroU64::new(VIEW_STRIDE),
                                }),
                            },
                            wgpu::BindGroupEntry { binding: 1, resource: planes.as_entire_binding() },
                        ],
                    });
                    (planes, bind_group)
                };
                Targets::Buffers { pages: (0..pages).map(page).collect() }
            }
            None => texture_targets(device, (side, pages), full, settings.depth),
        };
        let timestamps = timestamps.then(|| StampQueries::new(device));
        Self { side, pages, full, targets, readback, uniforms, bind_group, timestamps, last_used: 0 }
    }

    pub(super) fn page_bytes(&self) -> u64 {
        u64::from(self.side) * u64::from(self.side) * 4
    }

    pub(super) fn plane_bytes(&self) -> u64 {
        self.page_bytes() * u64::from(self.pages)
    }

    /// The bytes of the readback buffer that hold the first `used_pages` pages of every plane
    /// (the planes lie `plane_bytes` apart): where a batch of that many pages puts its
    /// timestamps, if it has them.
    pub(super) fn readback_bytes(&self, used_pages: u32) -> u64 {
        let planes = if self.full { 3 } else { 1 };
        (planes - 1) * self.plane_bytes() + u64::from(used_pages) * self.page_bytes()
    }

    /// What a batch of `used_pages` pages maps of the readback buffer: its pages, and its
    /// timestamps after them (in the last plane's unused pages, or past the last page).
    pub(super) fn mapped_bytes(&self, used_pages: u32) -> u64 {
        self.readback_bytes(used_pages) + if self.timestamps.is_some() { TIMESTAMP_BYTES } else { 0 }
    }
}

/// What a renderer's atlases are made with, the same for all of them.
#[derive(Clone, Copy, Debug)]
pub(super) struct AtlasSettings {
    /// Timestamp queries ([`super::RendererConfig::timestamps`] and the device's check).
    pub(super) timestamps: bool,
    /// The depth buffers of the graphics pipeline's passes.
    pub(super) depth: DepthBuffers,
}

/// The textures the graphics pipeline draws `pages` pages of `side` pixels into.
fn texture_targets(device: &wgpu::Device, (side, pages): (u32, u32), full: bool, depth: DepthBuffers) -> Targets {
    let texture = |label: &str, format, usage, layers: u32| {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
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
    let depth_layers = match depth {
        DepthBuffers::Shared => 1,
        DepthBuffers::PerPage => pages,
    };
    let depth = texture("esrp-render atlas depth", DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT, depth_layers);
    let extras = full.then(|| {
        Box::new([
            texture("esrp-render atlas view depth", DEPTH_OUT_FORMAT, target, pages),
            texture("esrp-render atlas segmentation", SEGMENT_FORMAT, target, pages),
        ])
    });
    Targets::Textures { colour, depth, extras }
}

/// The atlases not in use right now. A batch takes one out (or makes one), renders with it
/// without holding the lock, and puts it back: batches on different threads overlap (one
/// encodes and submits while another waits for the device or extracts its pixels).
pub(super) struct BatchState {
    pub(super) atlases: Vec<Atlas>,
    pub(super) batches: u64,
    /// Atlases made since the renderer was created (each one textures, buffers and a bind
    /// group allocated on the device).
    pub(super) created: u64,
}

impl BatchState {
    /// The pool, empty.
    pub(super) fn new() -> Self {
        Self { atlases: Vec::new(), batches: 0, created: 0 }
    }

    /// Takes out the smallest pooled atlas that holds `pages` pages of `side` pixels with the
    /// same planes (`full`), if any. A larger one serves as well as one of the exact size (a
    /// batch draws, copies and maps only the pages it uses), so batches whose sizes vary from
    /// one to the next (the server's, gathered as steps arrive) reuse a few atlases instead of
    /// making a new one for each size.
    pub(super) fn take(&mut self, side: u32, pages: u32, full: bool) -> Option<Atlas> {
        let best = (0..self.atlases.len())
            .filter(|&i| {
                let a = &self.atlases[i];
                a.side == side && a.full == full && a.pages >= pages
            })
            .min_by_key(|&i| self.atlases[i].pages)?;
        Some(self.atlases.swap_remove(best))
    }

    /// Puts `atlas` back, and drops the least recently used atlases beyond [`CACHED_ATLASES`].
    pub(super) fn put(&mut self, atlas: Atlas) {
        self.atlases.push(atlas);
        while self.atlases.len() > CACHED_ATLASES
            && let Some(oldest) = (0..self.atlases.len()).min_by_key(|&i| self.atlases[i].last_used)
        {
            self.atlases.swap_remove(oldest);
        }
    }
}

/// One page per view, every view at the page's origin: the viewport transform, and so
/// every rounding of rasterisation and interpolation, is the same whatever else is in the
/// batch. Returns the tiles (in request order), the page side (the largest resolution
/// rounded up to 64, so that rows are 256-byte aligned) and the number of pages (a power of
/// two, so that atlas shapes repeat across batches). `requests` fits one chunk.
pub(super) fn layout(requests: &[ViewRequest<'_>], max_pages: u32) -> (Vec<Tile>, u32, u32) {
    let largest = requests.iter().map(|r| r.resolution).max().unwrap_or(1);
    let side = largest.next_multiple_of(64);
    let tiles =
        requests.iter().enumerate().map(|(i, r)| Tile { page: i as u32, x: 0, y: 0, size: r.resolution }).collect();
    let pages = (requests.len() as u32).next_power_of_two().min(max_pages);
    (tiles, side, pages)
}

/// Splits a batch into consecutive chunks that each fit one atlas: at most `max_pages` (itself
/// at most [`CHUNK_VIEWS`](crate::CHUNK_VIEWS)) views and at most [`CHUNK_PIXELS`] page pixels
/// (a larger view alone).
pub(super) fn chunks(requests: &[ViewRequest<'_>], max_pages: u32) -> Vec<std::ops::Range<usize>> {
    let mut chunks = Vec::new();
    let (mut start, mut side) = (0usize, 0u64);
    for (i, request) in requests.iter().enumerate() {
        let wider = side.max(u64::from(request.resolution.next_multiple_of(64)));
        let views = (i + 1 - start) as u64;
        if i > start && (views > u64::from(max_pages) || views * wider * wider > CHUNK_PIXELS) {
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
