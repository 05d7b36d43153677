//! Images for people: PNG encoding, contact sheets, and a scene's start, goal and current views
//! in a few calls (what `esrp-dataset render` and the `render_scene` example use).

use std::sync::Arc;

use esrp_core::{CompiledScene, Episode, EpisodeConfig, ObjectPose};

use crate::camera::Camera;
use crate::error::RenderError;
use crate::mesh::BACKGROUND_COLOUR;
use crate::renderer::{Renderer, ViewRequest};

/// Encodes tightly packed RGB (3 bytes per pixel, row-major, top row first) as a PNG.
pub fn encode_png_rgb(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, RenderError> {
    encode_png(rgb, width, height, png::Compression::Balanced)
}

/// Encodes like [`encode_png_rgb`] with the encoder's fast compression: several times quicker
/// for somewhat larger files, for images made while someone waits (the web viewer's frames).
pub fn encode_png_rgb_fast(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, RenderError> {
    encode_png(rgb, width, height, png::Compression::Fast)
}

fn encode_png(rgb: &[u8], width: u32, height: u32, compression: png::Compression) -> Result<Vec<u8>, RenderError> {
    let expected = width as usize * height as usize * 3;
    if rgb.len() != expected {
        return Err(RenderError::Png {
            reason: format!("{} bytes given for {width}×{height} RGB ({expected})", rgb.len()),
        });
    }
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(compression);
    let png_error = |e: png::EncodingError| RenderError::Png { reason: e.to_string() };
    let mut writer = encoder.write_header().map_err(png_error)?;
    writer.write_image_data(rgb).map_err(png_error)?;
    writer.finish().map_err(png_error)?;
    Ok(out)
}

/// Decodes an 8-bit RGB or RGBA PNG into tightly packed RGB and its size.
pub fn decode_png_rgb(data: &[u8]) -> Result<(Vec<u8>, u32, u32), RenderError> {
    let png_error = |e: png::DecodingError| RenderError::Png { reason: e.to_string() };
    let decoder = png::Decoder::new(std::io::Cursor::new(data));
    let mut reader = decoder.read_info().map_err(png_error)?;
    let size = reader.output_buffer_size().ok_or_else(|| RenderError::Png { reason: "image too large".into() })?;
    let mut buffer = vec![0; size];
    let info = reader.next_frame(&mut buffer).map_err(png_error)?;
    buffer.truncate(info.buffer_size());
    let rgb = match (info.color_type, info.bit_depth) {
        (png::ColorType::Rgb, png::BitDepth::Eight) => buffer,
        (png::ColorType::Rgba, png::BitDepth::Eight) => {
            buffer.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect()
        }
        other => {
            return Err(RenderError::Png { reason: format!("unsupported PNG format {other:?}; expected 8-bit RGB") });
        }
    };
    Ok((rgb, info.width, info.height))
}

/// Lays out square RGB images of `resolution` pixels in a grid of `columns` columns with a
/// 2-pixel gutter in the background colour; returns the sheet's RGB and its width and height.
pub fn contact_sheet(images: &[&[u8]], resolution: u32, columns: u32) -> (Vec<u8>, u32, u32) {
    const GUTTER: u32 = 2;
    let columns = columns.clamp(1, images.len().max(1) as u32);
    let rows = (images.len() as u32).div_ceil(columns).max(1);
    let width = columns * resolution + (columns + 1) * GUTTER;
    let height = rows * resolution + (rows + 1) * GUTTER;
    let background = BACKGROUND_COLOUR.map(|c| (c * 255.0).round() as u8);
    let mut sheet: Vec<u8> = background.iter().copied().cycle().take(width as usize * height as usize * 3).collect();
    let n = resolution as usize;
    for (i, image) in images.iter().enumerate() {
        if image.len() != n * n * 3 {
            continue;
        }
        let (col, row) = (i as u32 % columns, i as u32 / columns);
        let x0 = (GUTTER + col * (resolution + GUTTER)) as usize;
        let y0 = (GUTTER + row * (resolution + GUTTER)) as usize;
        for y in 0..n {
            let dst = ((y0 + y) * width as usize + x0) * 3;
            sheet[dst..dst + n * 3].copy_from_slice(&image[y * n * 3..(y + 1) * n * 3]);
        }
    }
    (sheet, width, height)
}

/// A scene's three standard views as tightly packed RGB.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneViews {
    /// Width and height of each view, pixels.
    pub resolution: u32,
    /// The egocentric view at the start of an episode.
    pub ego: Vec<u8>,
    /// The goal image: the target layout, top-down.
    pub goal: Vec<u8>,
    /// The initial (current) layout, top-down.
    pub current: Vec<u8>,
}

/// Renders a scene's start egocentric view, goal image and current top-down view in one
/// batch (uploading the scene; fine for tools, wasteful in a server loop).
pub fn render_scene_views(
    renderer: &Renderer,
    scene: &Arc<CompiledScene>,
    resolution: u32,
) -> Result<SceneViews, RenderError> {
    let handle = renderer.upload_scene(scene)?;
    let episode = Episode::new(Arc::clone(scene), EpisodeConfig::default())
        .map_err(|e| RenderError::InvalidPoses { view: 0, reason: e.to_string() })?;
    let targets: Vec<ObjectPose> = scene.scene().movable_objects.iter().map(|o| o.target).collect();
    let current = episode.object_poses();
    let requests = [
        ViewRequest::new(&handle, Camera::Ego(episode.ego_camera()), current).with_resolution(resolution),
        ViewRequest::new(&handle, Camera::TopDown, &targets).with_resolution(resolution),
        ViewRequest::new(&handle, Camera::TopDown, current).with_resolution(resolution),
    ];
    let mut out = renderer.render_batch(&requests)?.into_iter().map(|v| v.rgb.to_vec());
    let mut next = || out.next().ok_or_else(|| RenderError::Readback { reason: "missing view".into() });
    Ok(SceneViews { resolution, ego: next()?, goal: next()?, current: next()? })
}

/// A scene's three standard views as PNG files' bytes.
#[derive(Clone, Debug, PartialEq)]
pub struct ScenePngs {
    /// `ego.png`: the egocentric view at the start of an episode.
    pub ego: Vec<u8>,
    /// `goal.png`: the target layout, top-down.
    pub goal: Vec<u8>,
    /// `current.png`: the initial layout, top-down.
    pub current: Vec<u8>,
}

/// [`render_scene_views`] encoded as PNG.
pub fn render_scene_pngs(
    renderer: &Renderer,
    scene: &Arc<CompiledScene>,
    resolution: u32,
) -> Result<ScenePngs, RenderError> {
    let views = render_scene_views(renderer, scene, resolution)?;
    let png = |rgb: &[u8]| encode_png_rgb(rgb, resolution, resolution);
    Ok(ScenePngs { ego: png(&views.ego)?, goal: png(&views.goal)?, current: png(&views.current)? })
}

/// A PNG contact sheet of the goal images of `scenes`, `columns` per row, rendered in batches.
pub fn goal_contact_sheet_png(
    renderer: &Renderer,
    scenes: &[Arc<CompiledScene>],
    resolution: u32,
    columns: u32,
) -> Result<Vec<u8>, RenderError> {
    let mut goals = Vec::with_capacity(scenes.len());
    for chunk in scenes.chunks(256) {
        let handles = chunk.iter().map(|s| renderer.upload_scene(s)).collect::<Result<Vec<_>, _>>()?;
        let targets: Vec<Vec<ObjectPose>> =
            chunk.iter().map(|s| s.scene().movable_objects.iter().map(|o| o.target).collect()).collect();
        let requests: Vec<ViewRequest<'_>> = handles
            .iter()
            .zip(&targets)
            .map(|(h, t)| ViewRequest::new(h, Camera::TopDown, t).with_resolution(resolution))
            .collect();
        goals.extend(renderer.render_batch(&requests)?.into_iter().map(|v| v.rgb));
    }
    let images: Vec<&[u8]> = goals.iter().map(|g| g.as_ref()).collect();
    let (sheet, width, height) = contact_sheet(&images, resolution, columns);
    encode_png_rgb(&sheet, width, height)
}
