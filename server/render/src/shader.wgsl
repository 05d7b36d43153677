// The graphics pipeline's shaders of esrp-render, appended to `view.wgsl` (the view's uniforms,
// `placed` and `lit`). Mirrors `gpu.rs` (`GpuVertex`): change both together.
//
// Lighting is computed per vertex from the face normal and passed flat, so the fragment stage
// only writes a constant: lavapipe's cost is per fragment, and flat shading needs nothing more.

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) slot: u32,
    @location(2) normal: vec3<f32>,
    @location(3) colour: u32,
    @location(4) segment: u32,
}

struct RgbOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) colour: vec4<f32>,
}

@vertex
fn vs_rgb(v: VertexIn) -> RgbOut {
    var out: RgbOut;
    out.clip = placed(v.position, v.slot).clip;
    out.colour = lit(v.normal, v.slot, v.colour);
    return out;
}

@fragment
fn fs_rgb(in: RgbOut) -> @location(0) vec4<f32> {
    return in.colour;
}

struct FullOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) colour: vec4<f32>,
    @location(1) depth: f32,
    @location(2) @interpolate(flat) segment: u32,
}

@vertex
fn vs_full(v: VertexIn) -> FullOut {
    let p = placed(v.position, v.slot);
    var out: FullOut;
    out.clip = p.clip;
    out.colour = lit(v.normal, v.slot, v.colour);
    out.depth = p.depth;
    out.segment = v.segment;
    return out;
}

// Depth goes out as the bits of an f32 in an R32Uint target: R32Float is not renderable on
// every backend (OpenGL ES), R32Uint is.
struct FullTargets {
    @location(0) colour: vec4<f32>,
    @location(1) depth_bits: u32,
    @location(2) segment: u32,
}

@fragment
fn fs_full(in: FullOut) -> FullTargets {
    var out: FullTargets;
    out.colour = in.colour;
    out.depth_bits = bitcast<u32>(in.depth);
    out.segment = in.segment;
    return out;
}
