//! Batching: a batch's outputs equal the views rendered one by one, whatever the mix.

use esrp_core::ObjectPose;
use esrp_render::{Camera, Outputs, ViewOutput, ViewRequest};

use crate::common::{
    bedroom, ego_at, one_box_room, own_renderer, pose, renderer, scattered_cameras, showcase, start, targets, uniform,
};

#[test]
fn batch_output_is_identical_to_views_rendered_one_by_one() {
    let (bed, show, boxes) = (bedroom(), showcase(), one_box_room(2.0, 2.0));
    let handles = [bed.clone(), show.clone(), boxes.clone()].map(|s| renderer().upload_scene(&s).unwrap());
    let (bed_cam, bed_now) = start(&bed);
    let (show_cam, show_now) = start(&show);
    let (bed_goal, show_goal) = (targets(&bed), targets(&show));
    let moved: Vec<ObjectPose> = vec![pose(4.0, 3.0, 0.7)];
    let mut requests = vec![
        ViewRequest::new(&handles[0], Camera::Ego(bed_cam), &bed_now),
        ViewRequest::new(&handles[1], Camera::TopDown, &show_goal),
        ViewRequest::new(&handles[2], Camera::Ego(ego_at(1.0, 1.0, 1)), &moved).with_outputs(Outputs::ALL),
        ViewRequest::new(&handles[0], Camera::TopDown, &bed_goal).with_resolution(64),
        ViewRequest::new(&handles[1], Camera::Ego(show_cam), &show_now).with_resolution(200),
        ViewRequest::new(&handles[2], Camera::TopDown, &moved)
            .with_outputs(Outputs { depth: true, segmentation: false }),
    ];
    for k in 0..16 {
        requests.push(ViewRequest::new(&handles[0], Camera::Ego(ego_at(1.0 + 0.2 * f64::from(k), 1.5, k)), &bed_now));
    }
    let batch = renderer().render_batch(&requests).unwrap();
    assert_eq!(batch.len(), requests.len());
    for (i, (request, batched)) in requests.iter().zip(&batch).enumerate() {
        let alone: ViewOutput = renderer().render_one(request).unwrap();
        assert_eq!(batched.resolution, request.resolution);
        assert_eq!(batched.rgb.len(), (request.resolution * request.resolution * 3) as usize);
        assert!(batched.rgb == alone.rgb, "view {i}: batched RGB differs from the view rendered alone");
        assert_eq!(batched.depth.is_some(), request.outputs.depth, "view {i}");
        assert_eq!(batched.segmentation.is_some(), request.outputs.segmentation, "view {i}");
        assert!(batched.depth == alone.depth, "view {i}: depth differs");
        assert!(batched.segmentation == alone.segmentation, "view {i}: segmentation differs");
    }
}

/// A full batch of views from all over a room, each compared bit for bit with the same view
/// rendered alone: where a view lands in a batch never changes a pixel (the server's
/// determinism under concurrency rests on this).
#[test]
fn a_full_batch_of_scattered_views_matches_views_rendered_alone() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let goal = targets(&scene);
    let cameras = scattered_cameras(0x2545_f491_4f6c_dd1d, esrp_render::CHUNK_VIEWS);
    let requests: Vec<_> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            if i % 7 == 3 {
                ViewRequest::new(&handle, Camera::TopDown, &goal)
            } else {
                ViewRequest::new(&handle, Camera::Ego(*c), &now)
            }
        })
        .collect();
    let batch = renderer().render_batch(&requests).unwrap();
    for (i, (request, batched)) in requests.iter().zip(&batch).enumerate() {
        let alone = renderer().render_one(request).unwrap();
        assert!(batched.rgb == alone.rgb, "view {i}: batched RGB differs from the view rendered alone");
    }
}

/// A batch beyond what one submission holds (more views than [`esrp_render::CHUNK_VIEWS`],
/// more pixels than [`esrp_render::CHUNK_PIXELS`]: both were errors when callers had to split)
/// is drawn in chunks, and every view equals the view rendered alone.
#[test]
fn a_batch_beyond_one_submission_is_chunked_and_matches_views_rendered_alone() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let goal = targets(&scene);
    let cameras = scattered_cameras(0x9e37_79b9_7f4a_7c15, esrp_render::CHUNK_VIEWS + 77);
    let mut requests: Vec<_> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let request = if i % 5 == 2 {
                ViewRequest::new(&handle, Camera::TopDown, &goal)
            } else {
                ViewRequest::new(&handle, Camera::Ego(*c), &now)
            };
            request.with_resolution(16 + 8 * (i % 3) as u32)
        })
        .collect();
    // Five views of 2048² (4 Mpixels each) are over the pixels of one submission together;
    // placed among the small ones, they also make chunks of mixed page sides.
    let large = 2048.min(renderer().max_resolution());
    for (k, at) in [3usize, 500, 501, 900, 1050].into_iter().enumerate() {
        let request = ViewRequest::new(&handle, Camera::Ego(cameras[k]), &now).with_resolution(large);
        requests.insert(at, if k == 1 { request.with_outputs(Outputs::ALL) } else { request });
    }
    let pixels: u64 = requests.iter().map(|r| u64::from(r.resolution).pow(2)).sum();
    assert!(requests.len() > esrp_render::CHUNK_VIEWS);
    assert!(large < 2048 || pixels > esrp_render::CHUNK_PIXELS, "{pixels} pixels");
    let batch = renderer().render_batch(&requests).unwrap();
    assert_eq!(batch.len(), requests.len());
    for (i, (request, batched)) in requests.iter().zip(&batch).enumerate() {
        let alone = renderer().render_one(request).unwrap();
        assert_eq!(batched.resolution, request.resolution, "view {i}");
        assert!(batched.rgb == alone.rgb, "view {i}: batched RGB differs from the view rendered alone");
        assert!(batched.depth == alone.depth, "view {i}: depth differs");
        assert!(batched.segmentation == alone.segmentation, "view {i}: segmentation differs");
    }
}

#[test]
fn full_batches_of_many_views_work_and_views_differ() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let cameras: Vec<_> =
        (0..256).map(|i| ego_at(0.8 + 0.013 * f64::from(i), 0.8 + 0.005 * f64::from(i), (i % 16) as u8)).collect();
    let requests: Vec<_> = cameras.iter().map(|c| ViewRequest::new(&handle, Camera::Ego(*c), &now)).collect();
    let out = renderer().render_batch(&requests).unwrap();
    assert_eq!(out.len(), 256);
    assert!(out.windows(2).all(|w| w[0].rgb != w[1].rgb), "neighbouring views differ");
    // Spot-check a few against single renders (the first test covers a mixed batch fully).
    for i in [0usize, 17, 255] {
        assert!(renderer().render_one(&requests[i]).unwrap().rgb == out[i].rgb, "view {i}");
    }
}

#[test]
fn renderer_is_usable_from_several_threads() {
    // Batches overlap across threads (each has its own atlas and uniforms): every thread's
    // views must still be exactly its own.
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let cameras: Vec<_> =
        (0..12).map(|k| ego_at(0.8 + 0.25 * f64::from(k), 1.2 + 0.1 * f64::from(k), k as u8)).collect();
    let expected: Vec<_> = cameras
        .iter()
        .map(|c| renderer().render_one(&ViewRequest::new(&handle, Camera::Ego(*c), &now)).unwrap().rgb)
        .collect();
    std::thread::scope(|s| {
        for t in 0..3usize {
            let (cameras, expected, handle, now) = (&cameras, &expected, &handle, &now);
            s.spawn(move || {
                for round in 0..6 {
                    // Thread t renders views t, t+3, ... in batches of a size of its own.
                    let mine: Vec<usize> = (0..12).filter(|i| (i + round) % 3 == t).collect();
                    let requests: Vec<_> =
                        mine.iter().map(|&i| ViewRequest::new(handle, Camera::Ego(cameras[i]), now)).collect();
                    let out = renderer().render_batch(&requests).unwrap();
                    for (&i, o) in mine.iter().zip(&out) {
                        assert!(o.rgb == expected[i], "thread {t}, round {round}: view {i} differs");
                    }
                }
            });
        }
    });
}

/// Culling (skipping the pieces an egocentric view cannot see) changes no pixel: views from
/// all over two rooms, in every direction, with the objects moved around (near the camera
/// too), give the same RGB, depth and segmentation bit for bit as a renderer that draws every
/// piece, and culling does skip work.
#[test]
fn culling_changes_no_pixel() {
    let everything = own_renderer(false);
    let mut unit = uniform(0x9e37_79b9_7f4a_7c15);
    let (mut drawn, mut total) = (0usize, 0usize);
    for scene in [bedroom(), showcase()] {
        let culled = renderer().upload_scene(&scene).unwrap();
        let full = everything.upload_scene(&scene).unwrap();
        let frame = culled.top_down_frame(128);
        let (lo_x, lo_z) = frame.pixel_to_floor(0.0, 128.0);
        let (hi_x, hi_z) = frame.pixel_to_floor(128.0, 0.0);
        let place = |unit: &mut dyn FnMut() -> f64| (lo_x + (hi_x - lo_x) * unit(), lo_z + (hi_z - lo_z) * unit());
        for i in 0..160 {
            let (x, z) = place(&mut unit);
            let camera = esrp_core::EgoCamera {
                eye: [x, 0.3 + 1.5 * unit(), z],
                yaw: std::f64::consts::TAU * unit(),
                pitch: (60.0 * unit() - 10.0f64).to_radians(),
                horizontal_fov: (50.0 + 60.0 * unit()).to_radians(),
            };
            let poses: Vec<ObjectPose> = (0..culled.movable_count())
                .map(|_| {
                    let (x, z) = place(&mut unit);
                    pose(x, z, std::f64::consts::TAU * unit())
                })
                .collect();
            let outputs = Outputs { depth: true, segmentation: true };
            let resolution = if i % 5 == 0 { 64 } else { 128 };
            let request = |handle| {
                ViewRequest::new(handle, Camera::Ego(camera), &poses).with_outputs(outputs).with_resolution(resolution)
            };
            let a = renderer().render_one(&request(&culled)).unwrap();
            let b = everything.render_one(&request(&full)).unwrap();
            assert!(a.rgb == b.rgb, "view {i}: culling changed the RGB image");
            assert_eq!(
                a.depth.map(|d| d.iter().map(|v| v.to_bits()).collect::<Vec<_>>()),
                b.depth.map(|d| d.iter().map(|v| v.to_bits()).collect::<Vec<_>>()),
                "view {i}: depth"
            );
            assert_eq!(a.segmentation, b.segmentation, "view {i}: segmentation");
            drawn += renderer().triangles_drawn(&request(&culled));
            total += everything.triangles_drawn(&request(&full));
        }
    }
    assert!(drawn * 4 < total * 3, "culling skipped too little: {drawn} of {total} triangles drawn");
}

/// Batches whose sizes vary from one to the next (the server's, gathered as steps arrive)
/// reuse the pooled atlases instead of allocating one for each size, and each view still equals
/// the view rendered alone. Only a larger batch, or one with other planes, makes another.
#[test]
fn batches_of_varying_sizes_reuse_the_pooled_atlases() {
    let own = own_renderer(true);
    let scene = bedroom();
    let handle = own.upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let cameras = scattered_cameras(0x5851_f42d_4c95_7f2d, 100);
    let alone: Vec<_> = cameras
        .iter()
        .map(|c| own.render_one(&ViewRequest::new(&handle, Camera::Ego(*c), &now)).unwrap().rgb)
        .collect();
    let made_by_singles = own.atlases_created();
    assert_eq!(made_by_singles, 1, "views rendered one by one share one atlas");
    let mut start_at = 0;
    for (round, size) in
        [64usize, 3, 17, 5, 33, 9, 2, 64, 40, 1, 20, 7, 63, 12].into_iter().cycle().take(42).enumerate()
    {
        let views: Vec<usize> = (0..size).map(|k| (start_at + k) % cameras.len()).collect();
        start_at += size;
        let requests: Vec<_> =
            views.iter().map(|&i| ViewRequest::new(&handle, Camera::Ego(cameras[i]), &now)).collect();
        let out = own.render_batch(&requests).unwrap();
        for (&i, o) in views.iter().zip(&out) {
            assert!(o.rgb == alone[i], "round {round} (a batch of {size}): view {i} differs from the view alone");
        }
    }
    assert_eq!(own.atlases_created(), made_by_singles + 1, "42 batches of 1 to 64 views: one more atlas (64 pages)");
    let requests: Vec<_> = cameras.iter().map(|c| ViewRequest::new(&handle, Camera::Ego(*c), &now)).collect();
    let out = own.render_batch(&requests).unwrap();
    assert!(out.iter().zip(&alone).all(|(o, a)| o.rgb == *a), "a batch of 100 matches the views alone");
    let with_depth = requests[0].with_outputs(Outputs { depth: true, segmentation: false });
    own.render_batch(&[with_depth, requests[1]]).unwrap();
    own.render_batch(&requests[..7]).unwrap();
    assert_eq!(own.atlases_created(), made_by_singles + 3, "a larger batch and one with depth make one each");
}

/// Batches submitted one after another without waiting (the device draws one while the next is
/// encoded), finished in any order and on other threads, give each view bit for bit as rendered
/// alone; a batch finished by another renderer is refused.
#[test]
fn batches_in_flight_together_match_views_rendered_alone() {
    let scene = bedroom();
    let handle = renderer().upload_scene(&scene).unwrap();
    let (_, now) = start(&scene);
    let goal = targets(&scene);
    let cameras = scattered_cameras(0x2f1b_8c3d_6a55_e0f7, 90);
    let request = |i: usize| {
        let r = if i % 9 == 4 {
            ViewRequest::new(&handle, Camera::TopDown, &goal)
        } else {
            ViewRequest::new(&handle, Camera::Ego(cameras[i]), &now)
        };
        if i % 11 == 5 { r.with_outputs(Outputs::ALL) } else { r }
    };
    let alone: Vec<ViewOutput> = (0..cameras.len()).map(|i| renderer().render_one(&request(i)).unwrap()).collect();
    // Four batches of different sizes (one with depth and segmentation), all in flight at once.
    let ranges = [0..7, 7..40, 40..41, 41..90];
    let submitted: Vec<_> = ranges
        .iter()
        .map(|range| {
            let requests: Vec<_> = range.clone().map(request).collect();
            renderer().submit_batch(&requests).unwrap()
        })
        .collect();
    let mut finished: Vec<Option<Vec<ViewOutput>>> = vec![None; ranges.len()];
    let mut submitted: Vec<_> = submitted.into_iter().enumerate().collect();
    // The last first, then the others on a thread each.
    let (last, batch) = submitted.pop().unwrap();
    let (out, timings) = renderer().finish_batch(batch).unwrap();
    assert!(timings.device > std::time::Duration::ZERO);
    finished[last] = Some(out);
    let others: Vec<(usize, Vec<ViewOutput>)> = std::thread::scope(|s| {
        let threads: Vec<_> = submitted
            .into_iter()
            .map(|(k, batch)| s.spawn(move || (k, renderer().finish_batch(batch).unwrap().0)))
            .collect();
        threads.into_iter().map(|t| t.join().unwrap()).collect()
    });
    for (k, out) in others {
        finished[k] = Some(out);
    }
    for (range, out) in ranges.iter().zip(finished) {
        let out = out.unwrap();
        assert_eq!(out.len(), range.len());
        for (i, o) in range.clone().zip(&out) {
            assert!(o.rgb == alone[i].rgb, "view {i}: RGB differs from the view rendered alone");
            assert!(o.depth == alone[i].depth, "view {i}: depth differs");
            assert!(o.segmentation == alone[i].segmentation, "view {i}: segmentation differs");
        }
    }
    let other = own_renderer(true);
    let batch = renderer().submit_batch(&[request(0)]).unwrap();
    let error = other.finish_batch(batch).unwrap_err();
    assert!(matches!(error, esrp_render::RenderError::ForeignBatch), "{error}");
}

/// A renderer timing its device (asked to: lavapipe and llvmpipe have timestamp queries) draws
/// the same images as one that does not, for batches that fill their atlas, leave pages of it
/// unused, span several chunks' worth of pages, and carry the extra planes; and says how long
/// the device drew, within the time the batch took on the thread. `auto` does not time a CPU
/// renderer.
#[test]
fn timing_the_device_changes_no_image_and_fits_in_the_batch() {
    use esrp_render::{RendererConfig, Timestamps};
    let with = |timestamps| crate::common::renderer_with(RendererConfig { timestamps, ..RendererConfig::default() });
    let (timed, untimed) = (with(Timestamps::On), with(Timestamps::Off));
    assert!(timed.times_device(), "the tests' adapter ({:?}) has timestamp queries", timed.adapter_info().backend);
    assert!(!untimed.times_device());
    assert!(timed.is_software() && !renderer().times_device(), "auto leaves a CPU renderer untimed");
    let scene = bedroom();
    let (handle, plain) = (timed.upload_scene(&scene).unwrap(), untimed.upload_scene(&scene).unwrap());
    let (_, now) = start(&scene);
    let cameras = scattered_cameras(0x51a7_0e11_c0de_0042, 40);
    // 4 views fill a 4-page atlas, 3 leave one page unused, 40 take 64 pages; then with depth and
    // segmentation (three planes: the timestamps go after the last plane's used pages).
    for (n, outputs) in [(4, Outputs::RGB), (3, Outputs::RGB), (40, Outputs::RGB), (3, Outputs::ALL), (4, Outputs::ALL)]
    {
        let requests = |h| -> Vec<ViewRequest<'_>> {
            cameras[..n].iter().map(|&c| ViewRequest::new(h, Camera::Ego(c), &now).with_outputs(outputs)).collect()
        };
        let started = std::time::Instant::now();
        let (out, timings) = timed.render_batch_timed(&requests(&handle)).unwrap();
        let wall = started.elapsed();
        let (expected, untimed_timings) = untimed.render_batch_timed(&requests(&plain)).unwrap();
        assert!(untimed_timings.gpu.is_none(), "{n} views: an untimed renderer reports no device time");
        let drawing = timings.gpu.unwrap_or_else(|| panic!("{n} views: no device time"));
        assert!(drawing > std::time::Duration::ZERO && drawing <= wall, "{n} views: drew {drawing:?} in {wall:?}");
        assert!(timings.total() <= wall, "{n} views: {timings:?} in {wall:?}");
        for (i, (a, b)) in out.iter().zip(&expected).enumerate() {
            assert!(a.rgb == b.rgb && a.depth == b.depth && a.segmentation == b.segmentation, "{n} views: view {i}");
        }
    }
}

/// A depth buffer per page draws the same images as the one every page clears in turn: batches
/// of one page, of several, of views that see each other's rooms' walls at other depths, and
/// with every plane.
#[test]
fn a_depth_buffer_per_page_draws_what_the_shared_one_draws() {
    use esrp_render::{DepthBuffers, Renderer, RendererConfig};
    let with =
        |depth_buffers| crate::common::renderer_with(RendererConfig { depth_buffers, ..RendererConfig::default() });
    let (shared, per_page) = (with(DepthBuffers::Shared), with(DepthBuffers::PerPage));
    let scenes = [bedroom(), showcase()];
    let handles = |r: &Renderer| scenes.iter().map(|s| r.upload_scene(s).unwrap()).collect::<Vec<_>>();
    let (on_shared, on_per_page) = (handles(&shared), handles(&per_page));
    let (_, bed_now) = start(&scenes[0]);
    let (_, show_now) = start(&scenes[1]);
    let cameras = scattered_cameras(0x0de9_7b00_ff17_3c5d, 37);
    // Every other view of each room, every fifth with every plane, then a top-down view.
    fn requests<'a>(
        h: &'a [std::sync::Arc<esrp_render::SceneHandle>],
        cameras: &[esrp_core::EgoCamera],
        poses: [&'a [ObjectPose]; 2],
    ) -> Vec<ViewRequest<'a>> {
        let mut views: Vec<ViewRequest<'a>> = cameras
            .iter()
            .enumerate()
            .map(|(i, &c)| {
                let view = ViewRequest::new(&h[i % 2], Camera::Ego(c), poses[i % 2]);
                if i % 5 == 0 { view.with_outputs(Outputs::ALL) } else { view }
            })
            .collect();
        views.push(ViewRequest::new(&h[0], Camera::TopDown, poses[0]));
        views
    }
    let poses = [bed_now.as_slice(), show_now.as_slice()];
    for n in [1, 2, 38] {
        let expected = shared.render_batch(&requests(&on_shared, &cameras, poses)[..n]).unwrap();
        let got = per_page.render_batch(&requests(&on_per_page, &cameras, poses)[..n]).unwrap();
        for (i, (e, g)) in expected.iter().zip(&got).enumerate() {
            assert!(e == g, "{n} views: view {i} differs with a depth buffer per page");
        }
    }
}
