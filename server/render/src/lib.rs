//! **esrp-render**: the ESRP renderer. It draws the observations of SPEC §2 and §4 — the
//! agent's egocentric RGB view and the top-down goal image — with wgpu, for many episodes at
//! once, on a GPU or on a CPU (Mesa's llvmpipe through OpenGL, or lavapipe through Vulkan) alike.
//!
//! One long-lived [`Renderer`] owns the device, the queue and the pipelines. Each scene is
//! turned into one triangle mesh and uploaded once ([`Renderer::upload_scene`] → an
//! `Arc<`[`SceneHandle`]`>`); each view names a scene, a [`Camera`] and the movable objects'
//! poses ([`ViewRequest`]). [`Renderer::render_batch`] draws any mix of views of any scenes into
//! the pages of an atlas (a texture array), one page and one render pass per view (a dynamic
//! uniform offset and one indexed draw per run of visible pieces), submits once, reads back once and returns
//! tightly packed RGB per view ([`ViewOutput`]), plus depth and segmentation where asked.
//!
//! # Invariants
//!
//! - **Batch-first, one submit per batch.** Rendering costs per submit and per draw, so callers
//!   batch across episodes; a batch's outputs are bit-identical to rendering each view alone.
//!   A batch may hold any number of views of any sizes: the renderer draws it in chunks of up
//!   to [`CHUNK_VIEWS`] views and [`CHUNK_PIXELS`] pixels (one submit each), so the batch
//!   limits have one owner and callers never split.
//!   Every view is drawn at the origin of its own page, so the viewport transform, and with it
//!   every rounding of rasterisation and interpolation, never depends on the rest of the batch
//!   (views packed side by side in one texture differ in the last bit of an interpolated
//!   colour now and then, which made observations depend on what else the server rendered).
//! - **Geometry is uploaded once.** A scene's mesh (floor, walls and doors, fixed furniture in
//!   the world frame, movable objects in their own frames) never changes. What changes per view
//!   is 240 bytes of uniforms: the camera and one pose per movable object, which the vertex
//!   shader applies. Writing them every batch is cheaper than tracking which moved.
//! - **Nothing panics on input.** Bad poses, resolutions, foreign scenes and a
//!   missing adapter are [`RenderError`] values; [`RenderError::NoAdapter`] says how to install
//!   Mesa's CPU renderers.
//! - **Culling changes no pixel.** An egocentric view skips the pieces (floor, wall pieces,
//!   objects) whose bounding spheres, grown by a margin far above f32 rounding, lie wholly
//!   outside its view volume; such a piece cannot touch a pixel ([`RendererConfig::cull`]).
//! - **Thread-safe.** [`Renderer`] and [`SceneHandle`] are `Send + Sync`; each batch renders
//!   with an atlas of its own from a small pool, so batches from two threads overlap (one
//!   submits while the other waits or extracts). [`Renderer::submit_batch`] returns once a
//!   batch is submitted and [`Renderer::finish_batch`] (on any thread) waits for it and
//!   extracts its views: one thread may keep several batches in flight, the device drawing one
//!   while the next is encoded, with the same outputs.
//! - **The agent is never drawn** (SPEC §2); there is no ceiling, so the background colour shows
//!   above the walls and through windows.
//!
//! # Module map
//!
//! - [`renderer`]: [`Renderer`], [`RendererConfig`], [`SceneHandle`], [`ViewRequest`],
//!   [`ViewOutput`], [`Outputs`]; the paged atlas (one page and one render pass per view,
//!   one submit per chunk of up to 16 Mpixels) and the readback.
//! - [`camera`]: [`Camera`], the egocentric projection ([`project_ego`]) and the top-down frame
//!   ([`TopDownFrame`]) with its exact pixel ↔ floor mapping.
//! - [`mesh`]: triangle meshes from esrp-core shapes (box: 12 triangles, cylinder: 12-sided
//!   prism, convex hull via parry, meshes as given, floor by ear clipping), colours and
//!   segmentation labels ([`SegmentLabel`]).
//! - [`images`]: PNG encoding, contact sheets, a scene's ego / goal / current views as PNG.
//! - `gpu`: the `#[repr(C)]` structs and the WGSL sources they mirror: `view.wgsl` (a view's
//!   uniforms, placement and lighting) before `shader.wgsl` (the graphics pipeline's shaders) or
//!   `raster.wgsl` (the compute rasteriser, [`Rasterizer::Compute`]).
//!
//! # Cameras and images
//!
//! Every image is `resolution × resolution` (128 by default), row-major, top row first; RGB is
//! 3 bytes per pixel. The **egocentric** camera is [`esrp_core::Episode::ego_camera`]: eye at
//! 1.25 m, pitched 20° down, 90° horizontal field of view, square pixels, near plane
//! [`camera::EGO_NEAR`] = 0.05 m. Depth is the view depth in metres along the camera's axis
//! (`dot(p − eye, forward)`), `f32::INFINITY` where nothing is drawn.
//!
//! The **top-down** view is orthographic, looking down −y, with image right = +x and image up
//! = −z (SPEC §1). It frames the bounding box of the floor and the walls plus
//! [`camera::TOP_DOWN_MARGIN`] (0.15 m) on each side, as a centred square of side `side`
//! metres ([`TopDownFrame::for_scene`]). With `m = side / resolution` metres per pixel and
//! continuous pixel coordinates (pixel `(c, r)` covers `[c, c+1) × [r, r+1)`, its centre is
//! `(c + 0.5, r + 0.5)`):
//!
//! ```text
//! col = (x − min_x) / m        x = min_x + col · m
//! row = (z − min_z) / m        z = min_z + row · m
//! ```
//!
//! [`TopDownFrame::floor_to_pixel`] and [`TopDownFrame::pixel_to_floor`] implement exactly this,
//! and the GPU projection is built from the same numbers.
//!
//! # Appearance
//!
//! Each movable category has a fixed saturated colour ([`mesh::category_colour`]: blue
//! cabinets/shelves/desks, red chairs, green sofas, yellow piers/stools, purple others) with a
//! small per-instance brightness tint by object index ([`mesh::movable_colour`]); floor, walls,
//! doors and fixed furniture are muted beige, off-white, brown and grey. Shading is flat: face
//! normals, one directional light from above plus ambient, computed per vertex and passed flat.
//!
//! # Golden images
//!
//! The tests compare renders with small PNGs in `server/render/tests/goldens/` with a tolerance
//! (a pixel differs when a channel differs by more than 2; at most 0.25 % of the pixels may
//! differ — robust to rounding and edge decisions of another rasteriser version, strict on
//! anything that moves, recolours or disappears). The same goldens pass on Vulkan and OpenGL. After an
//! intended change, regenerate them with
//! `ESRP_UPDATE_GOLDENS=1 cargo test -p esrp-render` and look at the new PNGs before committing.
//!
//! # Performance
//!
//! `cargo bench -p esrp-render` prints views/s for batches of 1, 16, 64 and 256 egocentric
//! views of furnished rooms (266 and 386 triangles) at 128×128, readback and RGB conversion
//! included, with culling on and off. On the 2-core development machine (AMD EPYC, no GPU,
//! Mesa 22.3.6, `LP_NUM_THREADS=0`, release build) lavapipe gives ~4,200 views/s one view per
//! call and 5,700–8,000 in batches; llvmpipe through OpenGL ~7,300 one view per call and
//! 5,600–8,100 in batches. `server/render/README.md` has the full table.

#![warn(missing_docs)]

pub mod camera;
mod error;
mod gpu;
pub mod images;
pub mod mesh;
pub mod renderer;

pub use camera::{Camera, TopDownFrame, project_ego};
pub use error::RenderError;
pub use images::{
    ScenePngs, SceneViews, contact_sheet, decode_png_rgb, encode_png_rgb, encode_png_rgb_fast, goal_contact_sheet_png,
    render_scene_pngs, render_scene_views,
};
pub use mesh::{SceneMesh, SegmentLabel, build_scene_mesh};
pub use renderer::{
    BackendPreference, CHUNK_PIXELS, CHUNK_VIEWS, DEFAULT_RESOLUTION, DepthBuffers, MAX_MOVABLE_OBJECTS, Outputs,
    Rasterizer, RenderTimings, Renderer, RendererConfig, SceneHandle, SubmittedBatch, Timestamps, UnknownBackend,
    UnknownDepthBuffers, UnknownRasterizer, UnknownTimestamps, ViewOutput, ViewRequest,
};

/// Re-export of wgpu, whose [`wgpu::AdapterInfo`] and [`wgpu::PowerPreference`] appear in this
/// crate's API.
pub use wgpu;
