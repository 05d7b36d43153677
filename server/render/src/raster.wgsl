// The compute rasteriser of esrp-render (`Rasterizer::Compute`): the same views as `shader.wgsl`
// draws through the graphics pipeline, drawn by compute shaders instead. Datacenter GPUs (the
// H100 and H200) carry little of the fixed-function graphics hardware (rasterisers, ROPs) that
// the graphics pipeline needs, and all of the compute units this needs.
//
// One workgroup of 16×16 invocations draws a 32×32 tile of one view, each invocation 2×2 pixels
// (one in each quadrant of the tile), so that a triangle is set up once per 1,024 pixels rather
// than per 256 (docs/performance.md, "The compute rasteriser"). The view's triangles are taken
// CHUNK at a time: each of the first CHUNK invocations places one triangle as the
// vertex shader does (`placed`, which both share), culls it (back face, wholly outside the view or
// the tile) and sets it up for 2D homogeneous rasterisation (Olano and Greer, 1997: no clipping,
// a triangle crossing the camera's plane included); then every invocation tests the chunk's kept
// triangles at its pixels' centres. A pixel keeps the nearest (reverse Z: the largest depth; depth
// outside [0, 1] is clipped away, as the near and far planes do) and among equals the first in
// draw order, as the graphics pipeline's depth test `Greater` does; so the result does not depend
// on the order in which triangles are kept. Colour and segmentation are the triangle's first
// vertex's (flat interpolation), the view depth is interpolated perspective-correct.
//
// Appended to `view.wgsl` (the view's uniforms, `placed` and `lit`, which the vertex shader uses
// too). Mirrors `gpu.rs` (`GpuVertex`): change both together. `BACKGROUND` is defined by the Rust
// side, prepended to the whole.

// A workgroup is GROUP × GROUP invocations; each draws SPAN × SPAN pixels, one in each of the
// tile's quadrants: a triangle is set up once per TILE × TILE pixels.
const GROUP: u32 = 16u;
const SPAN: u32 = 2u;
const PIXELS: u32 = SPAN * SPAN;
const TILE: u32 = GROUP * SPAN;
const CHUNK: u32 = 128u;
const VERTEX_WORDS: u32 = 9u;

// The view's page of the atlas, one u32 per pixel: colour (RGBA8), then with `full`, view depth
// (f32 bits) and segmentation, each side × side pixels.
@group(0) @binding(1) var<storage, read_write> planes: array<u32>;
@group(1) @binding(0) var<storage, read> vertices: array<u32>;
@group(1) @binding(1) var<storage, read> indices: array<u32>;

// A kept triangle: its three edge functions, depth and view depth as planes over the pixel's
// homogeneous coordinates (x, y, 1), each divided by the triangle's determinant.
struct Setup {
    e0: vec3<f32>,
    e1: vec3<f32>,
    e2: vec3<f32>,
    depth: vec3<f32>,
    view_depth: vec3<f32>,
}

var<workgroup> setups: array<Setup, CHUNK>;
// Colour, segment and triangle index of each kept triangle.
var<workgroup> flats: array<vec3<u32>, CHUNK>;
var<workgroup> kept: atomic<u32>;

fn word_f32(i: u32) -> f32 {
    return bitcast<f32>(vertices[i]);
}

// Vertex `v` placed in the view (`placed`).
fn place(v: u32) -> Placed {
    let b = v * VERTEX_WORDS;
    return placed(vec3<f32>(word_f32(b), word_f32(b + 1u), word_f32(b + 2u)), vertices[b + 3u]);
}

// As the vertex shader's colour of vertex `v` (`lit`), as an Rgba8Unorm target stores it.
fn shaded(v: u32) -> u32 {
    let b = v * VERTEX_WORDS;
    let normal = vec3<f32>(word_f32(b + 4u), word_f32(b + 5u), word_f32(b + 6u));
    return pack4x8unorm(lit(normal, vertices[b + 3u], vertices[b + 7u]));
}

// Places triangle `t`, culls it, and keeps its setup if it may cover a pixel of the tile whose
// pixel centres span `lo` to `hi` in a view of `size` pixels.
fn set_up(t: u32, lo: vec2<f32>, hi: vec2<f32>, size: f32) {
    let i0 = indices[3u * t];
    let i1 = indices[3u * t + 1u];
    let i2 = indices[3u * t + 2u];
    let a = place(i0);
    let b = place(i1);
    let c = place(i2);
    let x = vec3<f32>(a.clip.x, b.clip.x, c.clip.x);
    let y = vec3<f32>(a.clip.y, b.clip.y, c.clip.y);
    let z = vec3<f32>(a.clip.z, b.clip.z, c.clip.z);
    let w = vec3<f32>(a.clip.w, b.clip.w, c.clip.w);
    // Wholly outside one plane of the view volume.
    if all(x < -w) || all(x > w) || all(y < -w) || all(y > w) || all(z < vec3<f32>(0.0)) || all(z > w) {
        return;
    }
    // Homogeneous pixel coordinates: pixel (px, py) = (X / W, Y / W), y down.
    let h0 = vec3<f32>(0.5 * size * (a.clip.x + a.clip.w), 0.5 * size * (a.clip.w - a.clip.y), a.clip.w);
    let h1 = vec3<f32>(0.5 * size * (b.clip.x + b.clip.w), 0.5 * size * (b.clip.w - b.clip.y), b.clip.w);
    let h2 = vec3<f32>(0.5 * size * (c.clip.x + c.clip.w), 0.5 * size * (c.clip.w - c.clip.y), c.clip.w);
    let r0 = cross(h1, h2);
    let r1 = cross(h2, h0);
    let r2 = cross(h0, h1);
    let det = dot(h0, r0);
    // Counter-clockwise in clip space (front) is clockwise with y down: a negative determinant.
    // Back faces and degenerate triangles draw nothing.
    if !(det < 0.0) {
        return;
    }
    if all(w > vec3<f32>(0.0)) {
        let s0 = h0.xy / h0.z;
        let s1 = h1.xy / h1.z;
        let s2 = h2.xy / h2.z;
        let low = min(min(s0, s1), s2);
        let high = max(max(s0, s1), s2);
        if any(high < lo) || any(low > hi) {
            return;
        }
    }
    let inv = 1.0 / det;
    var setup: Setup;
    setup.e0 = r0 * inv;
    setup.e1 = r1 * inv;
    setup.e2 = r2 * inv;
    setup.depth = (z.x * r0 + z.y * r1 + z.z * r2) * inv;
    setup.view_depth = (a.depth * r0 + b.depth * r1 + c.depth * r2) * inv;
    let slot = atomicAdd(&kept, 1u);
    setups[slot] = setup;
    flats[slot] = vec3<u32>(shaded(i0), vertices[i0 * VERTEX_WORDS + 8u], t);
}

// Whether the pixel at `p` is inside the edge `e` (the value `v` there): positive inside; on the
// edge, the top-left rule (its inside lies right of it, or below a horizontal edge).
fn inside(e: vec3<f32>, v: f32) -> bool {
    return v > 0.0 || (v == 0.0 && (e.x > 0.0 || (e.x == 0.0 && e.y > 0.0)));
}

fn raster(tile: vec3<u32>, local: vec3<u32>, full: bool) {
    let size = view.tile.y;
    let triangles = view.tile.z;
    let origin = tile.xy * TILE;
    let lo = vec2<f32>(origin) + vec2<f32>(0.5);
    let hi = lo + vec2<f32>(f32(TILE - 1u));
    let thread = local.y * GROUP + local.x;
    // This invocation's pixels: (x, y) of the tile's GROUP × GROUP quadrants, quadrant by quadrant.
    var best_depth = array<f32, PIXELS>();
    var best = array<u32, PIXELS>();
    var colour = array<u32, PIXELS>();
    var segment = array<u32, PIXELS>();
    var view_depth = array<f32, PIXELS>();
    var p = array<vec3<f32>, PIXELS>();
    for (var q = 0u; q < PIXELS; q++) {
        let at = origin + local.xy + GROUP * vec2<u32>(q % SPAN, q / SPAN);
        p[q] = vec3<f32>(vec2<f32>(at) + vec2<f32>(0.5), 1.0);
        best[q] = 0xffffffffu;
        colour[q] = BACKGROUND;
    }
    for (var first = 0u; first < triangles; first += CHUNK) {
        if thread == 0u {
            atomicStore(&kept, 0u);
        }
        workgroupBarrier();
        if thread < CHUNK && first + thread < triangles {
            set_up(first + thread, lo, hi, f32(size));
        }
        workgroupBarrier();
        let count = atomicLoad(&kept);
        for (var k = 0u; k < count; k++) {
            let s = setups[k];
            let flat = flats[k];
            for (var q = 0u; q < PIXELS; q++) {
                let l0 = dot(s.e0, p[q]);
                let l1 = dot(s.e1, p[q]);
                let l2 = dot(s.e2, p[q]);
                if !(inside(s.e0, l0) && inside(s.e1, l1) && inside(s.e2, l2)) {
                    continue;
                }
                let depth = dot(s.depth, p[q]);
                if depth < 0.0 || depth > 1.0 {
                    continue;
                }
                if depth > best_depth[q] || (best[q] != 0xffffffffu && depth == best_depth[q] && flat.z < best[q]) {
                    best_depth[q] = depth;
                    best[q] = flat.z;
                    colour[q] = flat.x;
                    segment[q] = flat.y;
                    view_depth[q] = dot(s.view_depth, p[q]) / (l0 + l1 + l2);
                }
            }
        }
        workgroupBarrier();
    }
    let side = view.tile.w;
    let plane_words = side * side;
    for (var q = 0u; q < PIXELS; q++) {
        let at = origin + local.xy + GROUP * vec2<u32>(q % SPAN, q / SPAN);
        if at.x >= size || at.y >= size {
            continue;
        }
        let word = at.y * side + at.x;
        planes[word] = colour[q];
        if full {
            var depth = view_depth[q];
            if best[q] == 0xffffffffu {
                depth = 0.0;
            }
            planes[plane_words + word] = bitcast<u32>(depth);
            planes[2u * plane_words + word] = segment[q];
        }
    }
}

@compute @workgroup_size(16, 16, 1)
fn raster_rgb(@builtin(workgroup_id) tile: vec3<u32>, @builtin(local_invocation_id) local: vec3<u32>) {
    raster(tile, local, false);
}

@compute @workgroup_size(16, 16, 1)
fn raster_full(@builtin(workgroup_id) tile: vec3<u32>, @builtin(local_invocation_id) local: vec3<u32>) {
    raster(tile, local, true);
}
