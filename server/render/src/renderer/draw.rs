//! Drawing a chunk of views into an atlas and reading it back: one encoder, one submit, one
//! readback per chunk.

use std::time::{Duration, Instant};

use crate::camera::{Camera, EgoFrustum, ego_view, top_down_view};
use crate::error::RenderError;
use crate::gpu::{GpuView, VIEW_STRIDE};
use crate::mesh::BACKGROUND_COLOUR;

use super::atlas::{Atlas, PagedTexture, Targets, Tile, layout};
use super::clock::{TIMESTAMP_BYTES, drawing_time};
use super::device::Renderer;
use super::readback::{Planes, extract_all};
use super::requests::{Outputs, ViewOutput, ViewRequest};

impl Renderer {
    /// The runs of `request.scene`'s indices to draw for `request`: all of them, or with
    /// culling on, for an egocentric view, those of the pieces whose bounding spheres are not
    /// wholly outside the view volume (consecutive ones merged into one draw).
    pub(super) fn index_ranges(&self, request: &ViewRequest<'_>) -> Vec<std::ops::Range<u32>> {
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

    /// Renders a validated chunk of a batch with one submit and one readback; adds where its
    /// time went to `timings`.
    pub(super) fn render_chunk(
        &self,
        requests: &[ViewRequest<'_>],
        full: bool,
        timings: &mut RenderTimings,
    ) -> Result<Vec<ViewOutput>, RenderError> {
        let chunk = self.submit_chunk(requests, full, timings)?;
        self.finish_chunk(chunk, timings)
    }

    /// Takes an atlas for a validated chunk, draws `requests` into it (one page each), copies
    /// the pages to its readback buffer, submits, and asks for the buffer's mapping; returns
    /// without waiting for the device. Adds the encoding's time to `timings`. A validation
    /// error of the encoding or the submit is returned here.
    pub(super) fn submit_chunk(
        &self,
        requests: &[ViewRequest<'_>],
        full: bool,
        timings: &mut RenderTimings,
    ) -> Result<SubmittedChunk, RenderError> {
        let (tiles, side, pages) = layout(requests, self.max_pages);
        let t0 = Instant::now();
        let (taken, number) = {
            let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
            state.batches += 1;
            let taken = state.take(side, pages, full);
            if taken.is_none() {
                state.created += 1;
                timings.new_atlases += 1;
            }
            (taken, state.batches)
        };
        let mut atlas = taken.unwrap_or_else(|| {
            let compute = self.raster.as_ref().map(|raster| &raster.views_layout);
            Atlas::new(&self.device, &self.bind_group_layout, compute, (side, pages), full, self.atlas_settings())
        });
        atlas.last_used = number;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        self.queue.write_buffer(&atlas.uniforms, 0, &view_uniforms(requests, &tiles, side));
        let mut encoder =
            self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("esrp-render batch") });
        let used_pages = tiles.iter().map(|t| t.page + 1).max().unwrap_or(1);
        match (&atlas.targets, &self.raster) {
            (Targets::Buffers { pages }, Some(raster)) => {
                let timestamps = atlas.timestamps.as_ref().map(|t| &t.set);
                raster.encode(&mut encoder, pages, full, requests, &tiles, timestamps);
            }
            (Targets::Textures { colour, depth, extras }, _) => {
                self.draw_pages(&mut encoder, &atlas, colour, depth, extras.as_deref(), requests, &tiles, used_pages);
            }
            (Targets::Buffers { .. }, None) => {
                return Err(RenderError::Gpu { reason: "a compute atlas without the compute rasterizer".into() });
            }
        }
        copy_to_readback(&mut encoder, &atlas, used_pages);
        // The timestamps go behind the pages the batch maps, where no page of it is copied.
        let stamps_at = atlas.timestamps.as_ref().map(|t| {
            let at = atlas.readback_bytes(used_pages);
            encoder.resolve_query_set(&t.set, 0..2, &t.resolved, 0);
            encoder.copy_buffer_to_buffer(&t.resolved, 0, &atlas.readback, at, TIMESTAMP_BYTES);
            at
        });
        let encoded = Instant::now();
        let submission = self.queue.submit([encoder.finish()]);
        let bytes = atlas.mapped_bytes(used_pages);
        let (sender, mapped) = std::sync::mpsc::channel();
        atlas.readback.map_async(wgpu::MapMode::Read, 0..bytes, move |result| {
            let _ = sender.send(result);
        });
        let submitted = Instant::now();
        // Errors of the calls above are reported as they are made: the scope holds them all.
        if let Some(error) = pollster::block_on(scope.pop()) {
            // The atlas is dropped, not pooled: its mapping may still be pending.
            return Err(RenderError::Gpu { reason: error.to_string() });
        }
        timings.encode += encoded - t0;
        timings.submit += submitted - encoded;
        let outputs = requests.iter().map(|r| r.outputs).collect();
        Ok(SubmittedChunk { atlas, tiles, outputs, bytes, stamps_at, submission, mapped, submitted })
    }

    /// Waits for a chunk's submission and mapping, cuts every view out of the mapped buffer and
    /// puts the atlas back in the pool. Adds the device's and the extraction's times to
    /// `timings`. Says what went wrong if the chunk failed: a lost device, a failed poll or a
    /// buffer that could not be mapped.
    pub(super) fn finish_chunk(
        &self,
        chunk: SubmittedChunk,
        timings: &mut RenderTimings,
    ) -> Result<Vec<ViewOutput>, RenderError> {
        let SubmittedChunk { atlas, tiles, outputs, bytes, stamps_at, submission, mapped, submitted } = chunk;
        // Wait for this submission only: a later batch may still be running.
        let polled = self.device.poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None });
        // Another thread's poll may be the one that runs the map callback: wait for it a
        // little, polling again meanwhile, rather than assuming this poll ran it.
        let mut answer = None;
        if polled.is_ok() {
            let deadline = Instant::now() + Duration::from_secs(10);
            loop {
                match mapped.recv_timeout(Duration::from_millis(1)) {
                    Ok(result) => {
                        answer = Some(result.is_ok());
                        break;
                    }
                    Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                        answer = Some(false);
                        break;
                    }
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) if Instant::now() < deadline => {
                        let _ = self.device.poll(wgpu::PollType::Poll);
                    }
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => break,
                }
            }
        }
        let failure = if let Some(reason) = self.lost_reason() {
            Some(RenderError::DeviceLost { reason })
        } else if let Err(e) = polled {
            Some(RenderError::Readback { reason: e.to_string() })
        } else if answer != Some(true) {
            Some(RenderError::Readback { reason: "the readback buffer could not be mapped".into() })
        } else {
            None
        };
        if let Some(error) = failure {
            if answer == Some(true) {
                atlas.readback.unmap();
            }
            // An atlas whose mapping is still pending cannot be reused.
            if answer.is_some() {
                self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).put(atlas);
            }
            return Err(error);
        }
        let t2 = Instant::now();
        let stamps = stamps_at.zip(self.timestamp_period);
        let result = extract_mapped(&atlas, bytes, &outputs, &tiles, stamps);
        let t3 = Instant::now();
        timings.device += t2 - submitted;
        timings.extract += t3 - t2;
        let drawn = result.as_ref().ok().and_then(|(_, drawn)| *drawn);
        if let Some(drawn) = drawn {
            timings.gpu = Some(timings.gpu.unwrap_or_default() + drawn);
        }
        log::trace!(
            "esrp-render: {} views, {} pages of {}x{}: device {:?} (drawing {:?}), extract {:?}",
            outputs.len(),
            atlas.pages,
            atlas.side,
            atlas.side,
            t2 - submitted,
            drawn,
            t3 - t2
        );
        self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).put(atlas);
        result.map(|(views, _)| views)
    }

    /// Encodes one render pass per used page of `atlas`: each page cleared (the colour to the
    /// background, the extra planes to zero, its depth buffer to the far plane), then every view
    /// of that page drawn in its tile.
    #[allow(clippy::too_many_arguments)] // the atlas's targets, matched out by the caller
    fn draw_pages(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        atlas: &Atlas,
        colour: &PagedTexture,
        depth: &PagedTexture,
        extras: Option<&[PagedTexture; 2]>,
        requests: &[ViewRequest<'_>],
        tiles: &[Tile],
        used_pages: u32,
    ) {
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
            let mut attachments = vec![attachment(&colour.layers[page as usize], clear_colour)];
            if let Some(extras) = extras {
                attachments.push(attachment(&extras[0].layers[page as usize], wgpu::Color::TRANSPARENT));
                attachments.push(attachment(&extras[1].layers[page as usize], wgpu::Color::TRANSPARENT));
            }
            // The device's clock at the start of the first page and at the end of the last.
            let first = (page == 0).then_some(0);
            let last = (page + 1 == used_pages).then_some(1);
            let timestamp_writes = atlas.timestamps.as_ref().filter(|_| first.is_some() || last.is_some()).map(|t| {
                wgpu::RenderPassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: first,
                    end_of_pass_write_index: last,
                }
            });
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("esrp-render page"),
                color_attachments: &attachments,
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    // Its own layer, or the one every page clears in turn.
                    view: &depth.layers[page as usize % depth.layers.len()],
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Discard }),
                    stencil_ops: None,
                }),
                timestamp_writes,
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
    }
}

/// A chunk handed to the device ([`Renderer::submit_chunk`]) and not yet read back: its atlas
/// (out of the pool until [`Renderer::finish_chunk`]), where each view lies in it, what each
/// view asked for, and the pending submission and mapping.
pub(super) struct SubmittedChunk {
    atlas: Atlas,
    tiles: Vec<Tile>,
    outputs: Vec<Outputs>,
    /// The mapped bytes of the readback buffer.
    bytes: u64,
    /// Where in them the timestamps lie, if the renderer times the device.
    stamps_at: Option<u64>,
    submission: wgpu::SubmissionIndex,
    mapped: std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
    submitted: Instant,
}

/// Where a batch's time went on the thread that rendered it, summed over its chunks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderTimings {
    /// Taking an atlas, writing the views' uniforms and encoding the passes and copies.
    pub encode: Duration,
    /// Submitting the encoded commands and asking for the readback buffer's mapping (the
    /// driver's work on the calling thread).
    pub submit: Duration,
    /// From the submit's return until the readback buffer is mapped: the device drawing and
    /// copying (and, on a busy device, other threads' work before it), and the wait for it.
    pub device: Duration,
    /// The part of `device` the device spent drawing, by its own clock: from the start of a
    /// chunk's first pass to the end of its last (timestamp queries). `None` when the renderer
    /// does not time the device (the adapter lacks timestamp queries, or
    /// [`RendererConfig::timestamps`](crate::RendererConfig::timestamps) does not ask for them).
    pub gpu: Option<Duration>,
    /// Cutting each view's images out of the mapped buffer (RGBA to RGB, depth, segmentation).
    pub extract: Duration,
    /// Atlases made for the batch (none when the pool held one that fits each chunk).
    pub new_atlases: u32,
}

impl RenderTimings {
    /// The time on the calling thread: encoding, submitting, the device and extraction.
    pub fn total(&self) -> Duration {
        self.encode + self.submit + self.device + self.extract
    }
}

/// The per-view uniforms of `requests`, one [`VIEW_STRIDE`] apart: each view's camera and its
/// movable objects' poses, then (for the compute rasteriser) its target: page, resolution,
/// triangle count and the atlas's page `side`.
fn view_uniforms(requests: &[ViewRequest<'_>], tiles: &[Tile], side: u32) -> Vec<u8> {
    let mut uniforms = vec![0u8; requests.len() * VIEW_STRIDE as usize];
    for (i, (request, tile)) in requests.iter().zip(tiles).enumerate() {
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
        view.tile = [tile.page, tile.size, request.scene.index_count / 3, side];
        uniforms[start..start + std::mem::size_of::<GpuView>()].copy_from_slice(bytemuck::bytes_of(&view));
    }
    uniforms
}

/// Encodes the copies of `atlas`'s used pages into its readback buffer: the colour plane, then
/// the extra planes (depth and segmentation) where the atlas has them.
fn copy_to_readback(encoder: &mut wgpu::CommandEncoder, atlas: &Atlas, used_pages: u32) {
    let (colour, extras) = match &atlas.targets {
        Targets::Buffers { pages } => {
            // Each used page's planes to where the readback buffer holds them.
            let page_bytes = atlas.page_bytes();
            for (page, (planes, _)) in pages.iter().take(used_pages as usize).enumerate() {
                for plane in 0..if atlas.full { 3 } else { 1 } {
                    let to = plane * atlas.plane_bytes() + page as u64 * page_bytes;
                    encoder.copy_buffer_to_buffer(planes, plane * page_bytes, &atlas.readback, to, page_bytes);
                }
            }
            return;
        }
        Targets::Textures { colour, extras, .. } => (colour, extras),
    };
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
    copy(encoder, &colour.texture, 0);
    if let Some(extras) = extras {
        copy(encoder, &extras[0].texture, 1);
        copy(encoder, &extras[1].texture, 2);
    }
}

/// Every view (its `outputs` and tile) cut out of the first `bytes` of `atlas`'s readback buffer
/// (mapped), which is unmapped after, and with `stamps` (where the timestamps lie, and the
/// nanoseconds of a tick), how long the device took to draw them.
fn extract_mapped(
    atlas: &Atlas,
    bytes: u64,
    outputs: &[Outputs],
    tiles: &[Tile],
    stamps: Option<(u64, f32)>,
) -> Result<(Vec<ViewOutput>, Option<Duration>), RenderError> {
    let outputs = {
        let mapped =
            atlas.readback.get_mapped_range(..bytes).map_err(|e| RenderError::Readback { reason: format!("{e:?}") })?;
        let drawn = stamps.and_then(|(at, period)| drawing_time(mapped.get(at as usize..)?, period));
        let planes = Planes {
            bytes: &mapped,
            plane_bytes: atlas.plane_bytes() as usize,
            page_bytes: atlas.page_bytes() as usize,
            row_bytes: atlas.side as usize * 4,
            full: atlas.full,
        };
        extract_all(&planes, outputs, tiles).map(|views| (views, drawn))
    };
    atlas.readback.unmap();
    outputs
}
