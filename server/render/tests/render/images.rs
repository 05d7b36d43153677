//! Image helpers: PNG round trip, contact sheets, a scene's PNGs, and readable colours.

use esrp_core::MovableCategory;
use esrp_render::mesh::{self, BACKGROUND_COLOUR, DOOR_COLOUR, FIXED_COLOUR, FLOOR_COLOUR, WALL_COLOUR};
use esrp_render::{
    contact_sheet, decode_png_rgb, encode_png_rgb, encode_png_rgb_fast, goal_contact_sheet_png, render_scene_pngs,
};

use crate::common::{bedroom, one_box_room, renderer, showcase};

#[test]
fn png_round_trips() {
    let rgb: Vec<u8> = (0..5 * 3 * 3).map(|i| (i * 7) as u8).collect();
    let png = encode_png_rgb(&rgb, 5, 3).unwrap();
    assert_eq!(decode_png_rgb(&png).unwrap(), (rgb.clone(), 5, 3));
    assert!(encode_png_rgb(&[0; 5], 5, 3).is_err());
    let fast = encode_png_rgb_fast(&rgb, 5, 3).unwrap();
    assert_eq!(decode_png_rgb(&fast).unwrap(), (rgb, 5, 3));
    assert!(encode_png_rgb_fast(&[0; 5], 5, 3).is_err());
}

#[test]
fn contact_sheet_places_images_in_a_grid() {
    let a = vec![10u8; 4 * 4 * 3];
    let b = vec![200u8; 4 * 4 * 3];
    let (sheet, w, h) = contact_sheet(&[&a, &b, &a], 4, 2);
    assert_eq!((w, h), (2 * 4 + 3 * 2, 2 * 4 + 3 * 2));
    let px = |x: usize, y: usize| &sheet[(y * w as usize + x) * 3..][..3];
    assert_eq!(px(2, 2), [10, 10, 10]);
    assert_eq!(px(8, 2), [200, 200, 200]);
    assert_eq!(px(2, 8), [10, 10, 10]);
    assert_ne!(px(8, 8), [10, 10, 10]);
}

#[test]
fn scene_pngs_and_goal_sheet_render() {
    let pngs = render_scene_pngs(renderer(), &bedroom(), 128).unwrap();
    let (goal, current) = (&pngs.goal, &pngs.current);
    for png in [&pngs.ego, goal, current] {
        let (rgb, w, h) = decode_png_rgb(png).unwrap();
        assert_eq!((w, h, rgb.len()), (128, 128, 128 * 128 * 3));
    }
    assert_ne!(goal, current, "the bedroom's goal differs from its start");
    let sheet = goal_contact_sheet_png(renderer(), &[bedroom(), showcase(), one_box_room(3.0, 2.0)], 64, 2).unwrap();
    let (_, w, h) = decode_png_rgb(&sheet).unwrap();
    assert_eq!((w, h), (2 * 64 + 3 * 2, 2 * 64 + 3 * 2));
}

#[test]
fn movable_colours_are_distinct_from_each_other_and_from_the_room() {
    let distance = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    let room = [FLOOR_COLOUR, WALL_COLOUR, DOOR_COLOUR, FIXED_COLOUR, BACKGROUND_COLOUR];
    for (i, &a) in MovableCategory::ALL.iter().enumerate() {
        for index in 0..6 {
            let colour = mesh::movable_colour(a, index);
            for r in room {
                assert!(distance(colour, r) > 0.25, "{a:?} #{index} looks like the room");
            }
            for &b in &MovableCategory::ALL[i + 1..] {
                assert!(distance(colour, mesh::category_colour(b)) > 0.2, "{a:?} #{index} looks like {b:?}");
            }
        }
    }
}
