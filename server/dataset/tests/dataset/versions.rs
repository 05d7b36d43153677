//! The two versions of the built-in benchmark: esrp-bench-v1 pinned byte for byte, and
//! esrp-bench-v2's start poses (SPEC §7) against v1's scenes.

use esrp_core::{Action, CompiledScene, Episode, EpisodeConfig, PlanPoint, Rules};
use esrp_dataset::start::object_clearance;
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED, StartRule, check_start, validate_by_replay};

/// SHA-256 (FIPS 180-4), enough of it to pin files without a dependency.
fn sha256(bytes: &[u8]) -> String {
    const K: [u32; 64] = [
        0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5, 0xd807aa98,
        0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174, 0xe49b69c1, 0xefbe4786,
        0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da, 0x983e5152, 0xa831c66d, 0xb00327c8,
        0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967, 0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13,
        0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85, 0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819,
        0xd6990624, 0xf40e3585, 0x106aa070, 0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a,
        0x5b9cca4f, 0x682e6ff3, 0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7,
        0xc67178f2,
    ];
    let mut h: [u32; 8] =
        [0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19];
    let mut message = bytes.to_vec();
    message.push(0x80);
    while message.len() % 64 != 56 {
        message.push(0);
    }
    message.extend_from_slice(&(bytes.len() as u64 * 8).to_be_bytes());
    for block in message.chunks(64) {
        let mut w = [0u32; 64];
        for (i, word) in block.chunks(4).enumerate() {
            w[i] = u32::from_be_bytes([word[0], word[1], word[2], word[3]]);
        }
        for i in 16..64 {
            let s0 = w[i - 15].rotate_right(7) ^ w[i - 15].rotate_right(18) ^ (w[i - 15] >> 3);
            let s1 = w[i - 2].rotate_right(17) ^ w[i - 2].rotate_right(19) ^ (w[i - 2] >> 10);
            w[i] = w[i - 16].wrapping_add(s0).wrapping_add(w[i - 7]).wrapping_add(s1);
        }
        let [mut a, mut b, mut c, mut d, mut e, mut f, mut g, mut hh] = h;
        for i in 0..64 {
            let s1 = e.rotate_right(6) ^ e.rotate_right(11) ^ e.rotate_right(25);
            let ch = (e & f) ^ (!e & g);
            let t1 = hh.wrapping_add(s1).wrapping_add(ch).wrapping_add(K[i]).wrapping_add(w[i]);
            let s0 = a.rotate_right(2) ^ a.rotate_right(13) ^ a.rotate_right(22);
            let maj = (a & b) ^ (a & c) ^ (b & c);
            let t2 = s0.wrapping_add(maj);
            (hh, g, f, e, d, c, b, a) = (g, f, e, d.wrapping_add(t1), c, b, a, t1.wrapping_add(t2));
        }
        for (x, y) in h.iter_mut().zip([a, b, c, d, e, f, g, hh]) {
            *x = x.wrapping_add(y);
        }
    }
    h.iter().map(|x| format!("{x:08x}")).collect()
}

#[test]
fn sha256_matches_the_standard_vectors() {
    assert_eq!(sha256(b""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    assert_eq!(sha256(b"abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    let long = b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq";
    assert_eq!(sha256(long), "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
}

/// SHA-256 of `Scene::to_json_pretty()` of esrp-bench-v1 scenes (default seed), computed with the
/// generator as it was before esrp-bench-v2 existed (commit ff23369; `esrp-dataset show N` less
/// its final newline). esrp-bench-v1 is frozen: results are published on it. If this test
/// fails, something changed v1's scenes — the layout, the construction, the dice, the
/// catalogue, the scene format or esrp-core's stepping — and that change must not ship as v1.
///
/// The sample: every object count (1 to 6; 15 has 3, 108 and 168 have 4, 270 has 5, 146 has 6),
/// the README's scene 168, the planner's slowest scene 3437 and the last scene.
const V1_PINNED: [(usize, &str); 12] = [
    (0, "d94e84d521698dcd7872d2d7bb350cb9315eb2a9e642d2d573847a7f874b0fe9"),
    (1, "0c53ba6de7f0207b81d9f716822a6cbd9cb64496955d5a0f20c629e854780d66"),
    (2, "54dae72f9587b45edec61d39d1a6b6c263250c8cb5bc72f612a7fd50b76e1d4b"),
    (3, "40577f27ad3632d17c1c85b46e039afd63a4381f00cbd713daef8881d85c6651"),
    (15, "9364d3dd3d7ad7f7e825b48c96ff471f88b27a762c27a4179fc39c03a175e62b"),
    (42, "c2ac7e236dfc8bfb01444752592b5701c6a53c1a8ea9b88fa568cc6b9f1ec9b4"),
    (108, "df4027211293e182d88ad66129244a6b21a0748303cd717b575339a7e816c0a3"),
    (146, "6a416e440399541fedddbe7d7da6556211294449c7d10669e4e8f5a0b9345acb"),
    (168, "c83ebd8ab23dce7db15954e7298a96d0e0ad7dc735fb879539f04554b3760ffb"),
    (270, "e14ceb57d94e6bb6d56e077b45df7966eec6f7f6debf8183ede16c71f43215a4"),
    (3437, "82c29eb61ccfdb87d07d11f49c06f8a1522e79b2a59ed85b93ef38be2eec2f24"),
    (5494, "1247b3418622a6bf48fee203f20fffd33d00cd61c77c46c4f98051df7c47430d"),
];

#[test]
fn esrp_bench_v1_is_unchanged_byte_for_byte() {
    let bench = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
    for (index, hash) in V1_PINNED {
        let json = bench.generate(index).unwrap_or_else(|e| panic!("{e}")).scene.to_json_pretty();
        assert_eq!(sha256(json.as_bytes()), hash, "esrp-bench-v1/{index:05} changed");
    }
}

/// A spread of indices with every object count (1 to 6) among them.
fn sample_indices(bench: &Benchmark, per_count: usize) -> Vec<usize> {
    let mut chosen = Vec::new();
    for objects in 1..=6 {
        chosen.extend((0..bench.len()).filter(|&i| bench.object_count(i) == objects).take(per_count));
    }
    chosen
}

#[test]
fn esrp_bench_v2_is_v1_with_the_agent_started_away_from_every_object() {
    let v1 = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
    let v2 = Benchmark::new(BenchVersion::V2, DEFAULT_SEED);
    let rule = StartRule::default();
    let mut away = 0;
    for index in sample_indices(&v2, 2) {
        let old = v1.generate(index).unwrap_or_else(|e| panic!("{e}")).scene;
        let generated = v2.generate(index).unwrap_or_else(|e| panic!("{e}"));
        let new = generated.scene;
        let id = &new.id;
        assert_eq!(id, &format!("esrp-bench-v2/{index:05}"));
        // Same room, objects, layouts and split as v1.
        assert_eq!(new.split, old.split, "{id}");
        assert_eq!(new.room_type, old.room_type);
        assert_eq!(new.difficulty, old.difficulty);
        assert_eq!(new.room, old.room, "{id}");
        assert_eq!(new.fixed_objects, old.fixed_objects, "{id}");
        assert_eq!(new.movable_objects, old.movable_objects, "{id}");
        // The expert: the reversed drive (motions only), then v1's expert.
        let drive = new.expert_trajectory.len() - old.expert_trajectory.len();
        assert_eq!(new.expert_trajectory[drive..], old.expert_trajectory[..], "{id}");
        assert!(new.expert_trajectory[..drive].iter().all(|a| a.is_motion()), "{id}");
        assert_eq!(new.horizon, esrp_dataset::backward::horizon_for(new.expert_trajectory.len()));
        validate_by_replay(&new).unwrap_or_else(|e| panic!("{id}: {e}"));
        // The drive back ends exactly where v1 starts.
        let compiled = std::sync::Arc::new(CompiledScene::new(new.clone(), Rules::default()).unwrap());
        let mut episode = Episode::new(compiled.clone(), EpisodeConfig::default()).unwrap();
        for &a in &new.expert_trajectory[..drive] {
            assert!(episode.step(a).unwrap().accepted, "{id}: the drive back is rejected");
        }
        let pose = episode.agent_pose();
        assert!(pose.position.distance(PlanPoint::new(old.agent.x, old.agent.z)) < 1e-9, "{id}");
        assert_eq!(pose.heading, old.agent.heading, "{id}");
        assert_eq!(new.expert_trajectory[drive], Action::Fetch);
        // The rule of SPEC §7, as the generator reports it and as the validator checks it.
        let report = generated.start.expect("v2 reports its start");
        let poses: Vec<_> = new.movable_objects.iter().map(|o| o.pose).collect();
        let clearance = object_clearance(&compiled, &poses, PlanPoint::new(new.agent.x, new.agent.z));
        assert_eq!(clearance, report.clearance, "{id}");
        assert_eq!(report.drive, drive, "{id}");
        assert_eq!(report.fallback, clearance < rule.min_clearance, "{id}");
        assert_eq!(check_start(&new, &rule), Ok(clearance), "{id}");
        if !report.fallback {
            away += 1;
            assert!(clearance > Rules::default().fetch_reach);
        }
        // Generated alone, twice: the same bytes.
        assert_eq!(v2.generate(index).unwrap().scene.to_json_pretty(), new.to_json_pretty(), "{id}");
    }
    assert!(away >= 10, "only {away} of 12 sampled scenes start away from every object");
}

#[test]
fn the_validator_rejects_a_v2_start_within_reach() {
    let v1 = Benchmark::new(BenchVersion::V1, DEFAULT_SEED);
    let v2 = Benchmark::new(BenchVersion::V2, DEFAULT_SEED);
    let rule = StartRule::default();
    let index = (0..20).find(|&i| !v2.generate(i).unwrap().start.unwrap().fallback).expect("a scene with room");
    // A v2 scene that starts at v1's pose (with v1's expert): valid and replayable, but not v2.
    let mut scene = v1.generate(index).unwrap().scene;
    scene.id = v2.scene_id(index);
    validate_by_replay(&scene).unwrap();
    match check_start(&scene, &rule) {
        Err(esrp_dataset::StartViolation::TooClose { clearance, best, .. }) => {
            assert!(clearance <= Rules::default().fetch_reach && best >= rule.min_clearance, "{clearance} {best}");
        }
        other => panic!("{other:?}"),
    }
}
