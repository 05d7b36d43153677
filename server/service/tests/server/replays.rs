//! The web viewer's replays, against the real binary: a token keeps at most a few open, each is
//! freed with its episode, and the server's memory stays flat over a thousand replay cycles.

use super::harness::Server;

/// Starts a replay of `actions` on a test scene; returns its episode id.
async fn start_replay(server: &Server) -> Result<String, (u16, String)> {
    let body = r#"{"scene_id": "esrp-bench-v2/00003", "horizon": null, "actions": [2, 0, 3, 1]}"#;
    let (status, text) = server.viewer_request("POST", "/api/replay", None, body).await;
    if status != 200 {
        return Err((status, text));
    }
    let answer: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    Ok(answer["episode"].as_str().expect("an episode id").to_owned())
}

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("the server's status");
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS");
    line.split_whitespace().nth(1).and_then(|n| n.parse().ok()).expect("a size in kB")
}

#[tokio::test]
async fn replays_are_capped_per_token_and_freed_with_their_episode() {
    let server = Server::start(&["--http-listen", "127.0.0.1:0"]);
    // A few at once, then refused until one closes.
    let mut open = Vec::new();
    for _ in 0..4 {
        open.push(start_replay(&server).await.expect("a replay starts"));
    }
    let (status, message) = start_replay(&server).await.expect_err("a fifth is refused");
    assert_eq!(status, 429, "{message}");
    assert!(message.contains("replays open"), "{message}");
    let (status, _) = server.viewer_request("POST", &format!("/api/episodes/{}/close", open[0]), None, "").await;
    assert_eq!(status, 200);
    open[0] = start_replay(&server).await.expect("a closed replay gives its place back");
    for id in open {
        let (status, _) = server.viewer_request("POST", &format!("/api/episodes/{id}/close"), None, "").await;
        assert_eq!(status, 200);
    }

    // A thousand replay-and-close cycles: the memory after the first hundred stays where it is.
    let cycle = || async {
        let id = start_replay(&server).await.expect("a replay starts");
        let (status, _) =
            server.viewer_request("POST", &format!("/api/replay/{id}/seek"), None, r#"{"step": 4}"#).await;
        assert_eq!(status, 200);
        let (status, _) = server.viewer_request("POST", &format!("/api/episodes/{id}/close"), None, "").await;
        assert_eq!(status, 200);
    };
    for _ in 0..100 {
        cycle().await;
    }
    let warm = rss_kib(server.pid());
    for _ in 0..900 {
        cycle().await;
    }
    let after = rss_kib(server.pid());
    eprintln!("server RSS after 100 cycles {warm} KiB, after 1000 {after} KiB");
    assert!(after < warm + 16 * 1024, "RSS grew from {warm} KiB to {after} KiB over 900 replay cycles");
}
