//! Geometry: objects appear where the cameras predict, turning left shifts the scene right,
//! depth is right, and the top-down mapping is exact and oriented as SPEC §1 says.

use esrp_core::CompiledScene;
use esrp_render::{Camera, Outputs, SegmentLabel, TopDownFrame, ViewRequest, project_ego};

use crate::common::{ego_at, one_box_room, pixels_with, pose, renderer};

#[test]
fn top_down_mapping_round_trips_and_is_oriented() {
    let scene = one_box_room(3.0, 2.0);
    let frame = TopDownFrame::for_scene(&scene, 128);
    for (x, z) in [(0.0, 0.0), (6.0, 4.0), (1.234, 3.21)] {
        let (c, r) = frame.floor_to_pixel(x, z);
        let (x2, z2) = frame.pixel_to_floor(c, r);
        assert!((x - x2).abs() < 1e-12 && (z - z2).abs() < 1e-12);
    }
    // Image right is +x, image up is −z: the room's corner (0, 0) is at the top left.
    let (c0, r0) = frame.floor_to_pixel(0.0, 0.0);
    let (c1, r1) = frame.floor_to_pixel(6.0, 4.0);
    assert!(c0 < c1 && r0 < r1);
    // The room is centred and the margin is small: 6 m wide room plus walls and margins.
    assert!((c0 + c1 - 128.0).abs() < 1e-9 && (r0 + r1 - 128.0).abs() < 1e-9);
    assert!((frame.side - (6.0 + 2.0 * 0.12 + 2.0 * 0.15)).abs() < 1e-9, "side {}", frame.side);
    assert_eq!(frame.floor_to_pixel_index(3.0, 2.0), Some((64, 64)));
    let (x, z) = frame.pixel_centre_to_floor(64, 64);
    assert!(
        (x - 3.0 - frame.metres_per_pixel() / 2.0).abs() < 1e-12
            && (z - 2.0 - frame.metres_per_pixel() / 2.0).abs() < 1e-12
    );
}

fn top_down_box_centroid(scene: &CompiledScene, x: f64, z: f64, resolution: u32) -> (usize, (f64, f64)) {
    let handle = renderer().upload_scene(scene).unwrap();
    let poses = [pose(x, z, 0.0)];
    let out = renderer()
        .render_one(
            &ViewRequest::new(&handle, Camera::TopDown, &poses).with_outputs(Outputs::ALL).with_resolution(resolution),
        )
        .unwrap();
    pixels_with(out.segmentation.as_ref().unwrap(), resolution, SegmentLabel::Movable(0).id())
}

#[test]
fn object_appears_at_its_predicted_top_down_pixel() {
    let scene = one_box_room(1.0, 1.0);
    for (x, z) in [(1.0, 1.0), (4.5, 1.2), (2.2, 3.1)] {
        for resolution in [128, 200] {
            let frame = TopDownFrame::for_scene(&scene, resolution);
            let (n, centroid) = top_down_box_centroid(&scene, x, z, resolution);
            let expected = frame.floor_to_pixel(x, z);
            let side_px = 0.4 / frame.metres_per_pixel();
            assert!((n as f64 - side_px * side_px).abs() < 4.0 * side_px + 4.0, "{n} pixels for a {side_px} px square");
            assert!(
                (centroid.0 - expected.0).abs() < 0.5 && (centroid.1 - expected.1).abs() < 0.5,
                "box at ({x}, {z}) centred at pixel {centroid:?}, predicted {expected:?} ({resolution} px)"
            );
        }
    }
}

#[test]
fn object_appears_at_its_predicted_ego_pixel() {
    let scene = one_box_room(4.0, 2.0);
    let handle = renderer().upload_scene(&scene).unwrap();
    for (camera, target) in [
        (ego_at(1.5, 2.0, 0), [4.0, 0.2, 2.0]),
        (ego_at(1.5, 2.0, 0), [3.0, 0.2, 2.6]),
        (ego_at(4.0, 3.5, 4), [4.3, 0.2, 1.5]),
    ] {
        let poses = [pose(target[0], target[2], 0.0)];
        let out = renderer()
            .render_one(&ViewRequest::new(&handle, Camera::Ego(camera), &poses).with_outputs(Outputs::ALL))
            .unwrap();
        let seg = out.segmentation.as_ref().unwrap();
        let (n, centroid) = pixels_with(seg, 128, SegmentLabel::Movable(0).id());
        assert!(n > 20, "the box is visible ({n} pixels)");
        let (c, r, _) = project_ego(&camera, target, 128).unwrap();
        // The box's image centroid is near the projection of its centre (perspective moves it
        // by a fraction of the box's size).
        assert!(
            (centroid.0 - c).abs() < 2.5 && (centroid.1 - r).abs() < 2.5,
            "centroid {centroid:?}, predicted ({c}, {r})"
        );
        // The pixel containing the projection of the top face's centre shows the box.
        let (tc, tr, _) = project_ego(&camera, [target[0], 0.4, target[2]], 128).unwrap();
        let top = seg[tr as usize * 128 + tc as usize];
        assert_eq!(SegmentLabel::from_id(top), Some(SegmentLabel::Movable(0)));
    }
}

#[test]
fn turning_left_shifts_the_scene_right() {
    let scene = one_box_room(4.0, 2.0);
    let handle = renderer().upload_scene(&scene).unwrap();
    let poses = [pose(4.0, 2.0, 0.0)];
    let centroid = |heading| {
        let out = renderer()
            .render_one(
                &ViewRequest::new(&handle, Camera::Ego(ego_at(1.5, 2.0, heading)), &poses).with_outputs(Outputs::ALL),
            )
            .unwrap();
        pixels_with(out.segmentation.as_ref().unwrap(), 128, SegmentLabel::Movable(0).id()).1
    };
    let straight = centroid(0);
    let left = centroid(1);
    let right = centroid(15);
    assert!(left.0 > straight.0 + 10.0, "after turn_left the box moves right: {straight:?} → {left:?}");
    assert!(right.0 < straight.0 - 10.0, "after turn_right the box moves left: {straight:?} → {right:?}");
}

#[test]
fn depth_of_a_wall_at_a_known_distance_is_right() {
    // Agent at x = 3 facing +x; the wall's inner face is the plane x = 6 (3 m away).
    let scene = one_box_room(1.0, 1.0);
    let handle = renderer().upload_scene(&scene).unwrap();
    let camera = ego_at(3.0, 2.0, 0);
    let poses = [pose(1.0, 1.0, 0.0)];
    let out = renderer()
        .render_one(&ViewRequest::new(&handle, Camera::Ego(camera), &poses).with_outputs(Outputs::ALL))
        .unwrap();
    let depth = out.depth.as_ref().unwrap();
    let seg = out.segmentation.as_ref().unwrap();
    let mut checked = 0;
    for row in 0..128u32 {
        for col in 0..128u32 {
            let i = (row * 128 + col) as usize;
            if SegmentLabel::from_id(seg[i]) != Some(SegmentLabel::Wall) {
                continue;
            }
            // The ray through the pixel centre: a point at view depth 1 projects there, so the
            // wall's depth along the camera axis is 3 / (x-component of that point − eye).
            let u = (f64::from(col) + 0.5) / 64.0 - 1.0;
            let v = 1.0 - (f64::from(row) + 0.5) / 64.0;
            let (sp, cp) = camera.pitch.sin_cos();
            // forward (cp, −sp, 0), right (0, 0, 1), up (sp, cp, 0); hfov 90° so the focal scale is 1.
            let along_x = cp + v * sp;
            if along_x <= 0.0 {
                continue;
            }
            let hit_z = 2.0 + 3.0 / along_x * u;
            let hit_y = 1.25 + 3.0 / along_x * (-sp + v * cp);
            if !(0.1..3.9).contains(&hit_z) || !(0.05..2.55).contains(&hit_y) {
                continue; // corners and edges: another wall or the floor may own the pixel
            }
            let expected = 3.0 / along_x;
            let got = f64::from(depth[i]);
            assert!((got - expected).abs() / expected < 0.01, "pixel ({col}, {row}): depth {got}, expected {expected}");
            checked += 1;
        }
    }
    assert!(checked > 1000, "only {checked} wall pixels checked");
    // Above the walls nothing is drawn: infinite depth exactly where the label is background.
    assert!(seg.iter().any(|&s| s == SegmentLabel::Background.id()), "some sky above the far wall");
    for (d, s) in depth.iter().zip(seg) {
        assert_eq!(d.is_infinite(), *s == SegmentLabel::Background.id());
    }
}
