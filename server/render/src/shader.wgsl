// The one shader of esrp-render. Mirrors `gpu.rs` (`GpuVertex`, `GpuView`): change both together.
//
// Lighting is computed per vertex from the face normal and passed flat, so the fragment stage
// only writes a constant: lavapipe's cost is per fragment, and flat shading needs nothing more.

const MAX_POSE_SLOTS: u32 = 10u;
// Direction towards the light (normalised on the CPU side of the design: (0.35, 1.0, 0.6)).
const LIGHT: vec3<f32> = vec3<f32>(0.28746, 0.82130, 0.49278);
const AMBIENT: f32 = 0.55;
const DIFFUSE: f32 = 0.45;

struct View {
    // xyz: camera position in the world.
    eye: vec4<f32>,
    // xyz: image right; w: scale from view-space x to clip x.
    right: vec4<f32>,
    // xyz: image up; w: scale from view-space y to clip y.
    up: vec4<f32>,
    // xyz: viewing direction; view depth d = dot(p - eye, forward).
    forward: vec4<f32>,
    // clip.z = x * d + y, clip.w = z * d + w (reverse Z: nearer is larger).
    depth_map: vec4<f32>,
    // Per slot (cos yaw, sin yaw, x, z); slot 0 is the identity (static geometry).
    poses: array<vec4<f32>, MAX_POSE_SLOTS>,
}

@group(0) @binding(0) var<uniform> view: View;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) slot: u32,
    @location(2) normal: vec3<f32>,
    @location(3) colour: u32,
    @location(4) segment: u32,
}

struct Placed {
    clip: vec4<f32>,
    colour: vec4<f32>,
    depth: f32,
}

fn place(v: VertexIn) -> Placed {
    let pose = view.poses[min(v.slot, MAX_POSE_SLOTS - 1u)];
    let c = pose.x;
    let s = pose.y;
    let world = vec3<f32>(
        c * v.position.x + s * v.position.z + pose.z,
        v.position.y,
        -s * v.position.x + c * v.position.z + pose.w,
    );
    let normal = vec3<f32>(c * v.normal.x + s * v.normal.z, v.normal.y, -s * v.normal.x + c * v.normal.z);
    let rel = world - view.eye.xyz;
    let d = dot(rel, view.forward.xyz);
    var out: Placed;
    out.clip = vec4<f32>(
        dot(rel, view.right.xyz) * view.right.w,
        dot(rel, view.up.xyz) * view.up.w,
        view.depth_map.x * d + view.depth_map.y,
        view.depth_map.z * d + view.depth_map.w,
    );
    let shade = AMBIENT + DIFFUSE * max(dot(normal, LIGHT), 0.0);
    out.colour = vec4<f32>(unpack4x8unorm(v.colour).rgb * shade, 1.0);
    out.depth = d;
    return out;
}

struct RgbOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) colour: vec4<f32>,
}

@vertex
fn vs_rgb(v: VertexIn) -> RgbOut {
    let p = place(v);
    var out: RgbOut;
    out.clip = p.clip;
    out.colour = p.colour;
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
    let p = place(v);
    var out: FullOut;
    out.clip = p.clip;
    out.colour = p.colour;
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
