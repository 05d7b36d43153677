//! Turning the read-back planes of an atlas into each view's images.

use bytes::Bytes;

use crate::error::RenderError;

use super::atlas::Tile;
use super::requests::{Outputs, ViewOutput};

/// The mapped readback buffer: one plane per output texture, rows of `row_bytes`.
pub(super) struct Planes<'a> {
    pub(super) bytes: &'a [u8],
    pub(super) plane_bytes: usize,
    pub(super) page_bytes: usize,
    pub(super) row_bytes: usize,
    pub(super) full: bool,
}

impl Planes<'_> {
    /// The `row`-th row of `tile` in `plane`, 4 bytes per pixel.
    pub(super) fn row(&self, plane: usize, tile: &Tile, row: usize) -> &[u8] {
        let start = plane * self.plane_bytes
            + tile.page as usize * self.page_bytes
            + (tile.y as usize + row) * self.row_bytes
            + tile.x as usize * 4;
        &self.bytes[start..start + tile.size as usize * 4]
    }

    pub(super) fn words(&self, plane: usize, tile: &Tile) -> Vec<u32> {
        let n = tile.size as usize;
        let mut out = vec![0u32; n * n];
        for (row, dst) in out.chunks_exact_mut(n).enumerate() {
            for (d, s) in dst.iter_mut().zip(self.row(plane, tile, row).chunks_exact(4)) {
                *d = u32::from_le_bytes([s[0], s[1], s[2], s[3]]);
            }
        }
        out
    }

    pub(super) fn extract(&self, outputs: Outputs, tile: &Tile) -> ViewOutput {
        let n = tile.size as usize;
        let mut rgb = vec![0u8; n * n * 3];
        for (row, dst) in rgb.chunks_exact_mut(n * 3).enumerate() {
            rgba_to_rgb(self.row(0, tile, row), dst);
        }
        let depth = (outputs.depth && self.full).then(|| {
            self.words(1, tile)
                .into_iter()
                .map(|bits| {
                    let d = f32::from_bits(bits);
                    if d > 0.0 { d } else { f32::INFINITY }
                })
                .collect()
        });
        let segmentation = (outputs.segmentation && self.full).then(|| self.words(2, tile));
        ViewOutput { resolution: tile.size, rgb: Bytes::from(rgb), depth, segmentation }
    }
}

/// Drops the alpha byte of each pixel: `src` is RGBA, `dst` RGB, same pixel count. Four
/// pixels at a time as three little-endian words, which compiles to a tight loop.
pub(super) fn rgba_to_rgb(src: &[u8], dst: &mut [u8]) {
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
pub(super) fn extract_all(
    planes: &Planes<'_>,
    outputs: &[Outputs],
    tiles: &[Tile],
) -> Result<Vec<ViewOutput>, RenderError> {
    const PIXELS_PER_THREAD: u64 = 1 << 18;
    let pixels: u64 = tiles.iter().map(|t| u64::from(t.size).pow(2)).sum();
    // available_parallelism reads cgroup files on every call: ask once.
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    let threads = (*CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))).min(8);
    let threads = threads.min((pixels / PIXELS_PER_THREAD) as usize).max(1);
    if threads == 1 {
        return Ok(outputs.iter().zip(tiles).map(|(o, t)| planes.extract(*o, t)).collect());
    }
    let chunk = outputs.len().div_ceil(threads);
    std::thread::scope(|scope| {
        // The calling thread takes the first chunk; helpers take the rest.
        let workers: Vec<_> = outputs
            .chunks(chunk)
            .zip(tiles.chunks(chunk))
            .skip(1)
            .map(|(os, ts)| {
                scope.spawn(move || os.iter().zip(ts).map(|(o, t)| planes.extract(*o, t)).collect::<Vec<_>>())
            })
            .collect();
        let first = outputs.len().min(chunk);
        let mut out: Vec<ViewOutput> =
            outputs[..first].iter().zip(&tiles[..first]).map(|(o, t)| planes.extract(*o, t)).collect();
        for worker in workers {
            out.extend(
                worker.join().map_err(|_| RenderError::Readback { reason: "an extraction thread panicked".into() })?,
            );
        }
        Ok(out)
    })
}
