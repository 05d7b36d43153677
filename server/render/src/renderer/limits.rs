//! The sizes the renderer works in: the default resolution, how much one submit draws, how many
//! movable objects a scene may have and how many atlases are kept.

use crate::gpu::MAX_POSE_SLOTS;

/// Resolution of every view unless a request asks for another (SPEC §2, §4).
pub const DEFAULT_RESOLUTION: u32 = 128;
/// Most views drawn with one submit (1024 views of 128×128, fewer of larger views): a
/// [`Renderer::render_batch`](crate::Renderer::render_batch) of more is drawn in consecutive
/// chunks. Callers that gather work for the renderer may use it as the size worth gathering; it
/// is not a limit.
pub const CHUNK_VIEWS: usize = 1024;
/// Most page pixels drawn with one submit (1024 views of 128×128); a single view larger than
/// this is drawn alone.
pub const CHUNK_PIXELS: u64 = 1 << 24;
/// Most movable objects a scene may have for this renderer (pose slots on the GPU).
pub const MAX_MOVABLE_OBJECTS: usize = MAX_POSE_SLOTS - 1;
/// Atlas textures kept for reuse (one per distinct size and output set).
pub(super) const CACHED_ATLASES: usize = 4;
