//! Arbitrary bytes as an `esrp.scene/v1` document: parsing ([`Scene::from_json`]) and
//! validation ([`CompiledScene::new`], which also builds the collision world) must answer
//! `Ok` or a typed error, never panic, hang or overflow. A scene that validates must survive
//! its own JSON: printed, parsed back equal, and valid again.

#![no_main]

use esrp_core::{CompiledScene, Rules, Scene};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // Scene files and the gRPC `scene_json` field are UTF-8 text.
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(scene) = Scene::from_json(text) else { return };
    if CompiledScene::new(scene.clone(), Rules::default()).is_err() {
        return;
    }
    let printed = scene.to_json_pretty();
    let again = Scene::from_json(&printed).expect("a valid scene's own JSON parses");
    assert_eq!(again, scene, "a valid scene changed through its own JSON");
    CompiledScene::new(again, Rules::default()).expect("a valid scene's own JSON validates");
});
