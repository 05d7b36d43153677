// A view's uniforms, and how a vertex is placed and lit in it: the part of esrp-render's shaders
// that the graphics pipeline (`shader.wgsl`) and the compute rasteriser (`raster.wgsl`) share,
// each source appended to this one (`gpu.rs`). Mirrors `gpu.rs` (`GpuView`): change both together.

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
    // The compute rasteriser's target: x, the view's page in the atlas; y, its resolution; z,
    // its scene's triangles; w, the page side (pixels).
    tile: vec4<u32>,
}

@group(0) @binding(0) var<uniform> view: View;

// A vertex placed in the view: its clip position and its view depth.
struct Placed {
    clip: vec4<f32>,
    depth: f32,
}

fn pose(slot: u32) -> vec4<f32> {
    return view.poses[min(slot, MAX_POSE_SLOTS - 1u)];
}

// The vertex at `position` in the frame of pose `slot`, placed in the view.
fn placed(position: vec3<f32>, slot: u32) -> Placed {
    let p = pose(slot);
    let c = p.x;
    let s = p.y;
    let world = vec3<f32>(
        c * position.x + s * position.z + p.z,
        position.y,
        -s * position.x + c * position.z + p.w,
    );
    let rel = world - view.eye.xyz;
    let d = dot(rel, view.forward.xyz);
    var out: Placed;
    out.clip = vec4<f32>(
        dot(rel, view.right.xyz) * view.right.w,
        dot(rel, view.up.xyz) * view.up.w,
        view.depth_map.x * d + view.depth_map.y,
        view.depth_map.z * d + view.depth_map.w,
    );
    out.depth = d;
    return out;
}

// The colour `colour` (RGBA8) of a face whose normal is `normal` in the frame of pose `slot`, lit.
fn lit(normal: vec3<f32>, slot: u32, colour: u32) -> vec4<f32> {
    let p = pose(slot);
    let c = p.x;
    let s = p.y;
    let n = vec3<f32>(c * normal.x + s * normal.z, normal.y, -s * normal.x + c * normal.z);
    let shade = AMBIENT + DIFFUSE * max(dot(n, LIGHT), 0.0);
    return vec4<f32>(unpack4x8unorm(colour).rgb * shade, 1.0);
}
