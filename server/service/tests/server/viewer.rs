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
