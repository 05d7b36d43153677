//! The web viewer's JSON API, against the real binary: every failure is a JSON `{"error"}` with a
//! fitting status, malformed requests, unknown routes and wrong methods included.

use super::harness::Server;

/// The `error` of a JSON error answer; fails the test if the body is not one.
fn error_of(status: u16, body: &str) -> String {
    let value: serde_json::Value =
        serde_json::from_str(body).unwrap_or_else(|e| panic!("a {status} answer is not JSON ({e}): {body:?}"));
    value["error"].as_str().unwrap_or_else(|| panic!("no error message in {body}")).to_owned()
}

#[tokio::test]
async fn every_api_failure_is_json() {
    let server = Server::start(&["--http-listen", "127.0.0.1:0"]);
    let cases: [(&str, &str, &str, u16, &str); 8] = [
        ("POST", "/api/play", "not json", 400, "JSON"),
        ("POST", "/api/play", r#"{"scen": "x"}"#, 422, "missing field `scene`"),
        ("POST", "/api/episodes/e/step", r#"{"action": 300}"#, 422, "action"),
        ("POST", "/api/replay/e/seek", r#"{"step": -1}"#, 422, "step"),
        ("GET", "/api/records/alice/abc", "", 400, "abc"),
        ("GET", "/api/records?scene=a&scene=b", "", 400, "scene"),
        ("GET", "/api/nothing-here", "", 404, "no such API route"),
        ("GET", "/api/play", "", 405, "wrong method"),
    ];
    for (method, path, body, status, says) in cases {
        let (got, text) = server.viewer_request(method, path, None, body).await;
        assert_eq!(got, status, "{method} {path}: {text}");
        let message = error_of(got, &text);
        assert!(message.contains(says), "{method} {path}: {message:?} does not say {says:?}");
    }
    // The handlers' own failures stay as they were.
    let (status, text) = server.viewer_request("POST", "/api/play", None, r#"{"scene": "x"}"#).await;
    assert_eq!(status, 404);
    assert!(error_of(status, &text).contains("no scene \"x\""), "{text}");
    // The page itself is still HTML.
    let (status, text) = server.viewer_request("GET", "/", None, "").await;
    assert_eq!(status, 200);
    assert!(text.starts_with("<!doctype html>"), "{text}");
}

#[tokio::test]
async fn the_scene_list_says_how_many_match_and_narrows_by_id() {
    let server = Server::start(&["--http-listen", "127.0.0.1:0"]);
    let scenes = |query: &'static str| {
        let server = &server;
        async move {
            let (status, text) = server.viewer_request("GET", &format!("/api/scenes?{query}"), None, "").await;
            assert_eq!(status, 200, "{text}");
            serde_json::from_str::<serde_json::Value>(&text).expect("JSON")
        }
    };
    // The train split has more scenes than a list holds: the first 1,000, and how many there are.
    let train = scenes("split=train").await;
    assert_eq!(train["scenes"].as_array().expect("a list").len(), 1000);
    assert!(train["total"].as_u64().expect("a total") > 1000, "{}", train["total"]);
    // Part of an id narrows it to the scenes whose id holds it.
    let test = scenes("split=test&difficulty=easy").await;
    let id = test["scenes"][2]["id"].as_str().expect("an id").to_owned();
    let (status, text) =
        server.viewer_request("GET", &format!("/api/scenes?split=test&id={}", id.replace('/', "%2F")), None, "").await;
    assert_eq!(status, 200, "{text}");
    let found: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    assert_eq!(found["total"], 1, "{found}");
    assert_eq!(found["scenes"][0]["id"], id.as_str());
    // A split or difficulty that does not exist is refused, not answered with an empty list.
    for (query, says) in [
        ("split=tets", "\"tets\" is not a split: use train, test, challenge or minival"),
        ("split=test&difficulty=EASY", "\"EASY\" is not a difficulty: use easy, medium or hard"),
    ] {
        let (status, text) = server.viewer_request("GET", &format!("/api/scenes?{query}"), None, "").await;
        assert_eq!(status, 400, "{query}: {text}");
        let error: serde_json::Value = serde_json::from_str(&text).expect("JSON");
        assert_eq!(error["error"], says, "{query}");
    }
    // Empty values still mean "any".
    assert_eq!(scenes("split=test&difficulty=").await["total"], scenes("split=test").await["total"]);
}
