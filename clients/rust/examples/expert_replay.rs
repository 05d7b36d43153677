//! Replays the expert trajectory of a few test scenes: reads each scene's trajectory from the
//! privileged state (the scene JSON), sends it on a pipelined stream, and prints SR / OSR / RDR.
//! Every expert trajectory must succeed: anything less is a bug.
//!
//! ```sh
//! cargo run -p esrp-client --example expert_replay -- [SERVER_URL] [SCENES]
//! ```

use esrp_client::{Client, EpisodeOptions, LocalServer, SceneFilter, Split};
use tokio_stream::StreamExt;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    // A server's URL (`http://host:port`, `unix:PATH`), else a server started here.
    let (address, _local) = match args.next().filter(|a| a.contains("://") || a.starts_with("unix:")) {
        Some(address) => (address, None),
        None => {
            let local = LocalServer::start::<&str>(None, &[])?;
            (local.address.clone(), Some(local))
        }
    };
    let count: usize = std::env::args().filter_map(|a| a.parse().ok()).next().unwrap_or(5);
    let client = Client::connect(&address).await?;
    let scenes: Vec<_> = client.scenes(SceneFilter::split(Split::Test)).take(count).collect::<Result<_, _>>().await?;
    let (mut successes, mut osr, mut rdr) = (0, 0.0, 0.0);
    for scene in &scenes {
        let (episode, _) = client.create_episode(EpisodeOptions::scene(&scene.id).privileged(true)).await?;
        let actions = episode.privileged_state().await?.expert_trajectory()?;
        // All steps in flight at once: a replay needs no observation to choose its next action.
        let mut stream = client.episode_stream(actions.len().max(1)).await?;
        let results = stream.run(&[(episode.id(), &actions)]).await?.remove(0);
        let last = results.into_iter().last().transpose()?;
        let metrics = match last.and_then(|r| r.metrics) {
            Some(m) => m,
            None => episode.metrics().await?.0,
        };
        episode.close().await?;
        successes += u32::from(metrics.success);
        osr += metrics.object_success_rate;
        rdr += metrics.remaining_distance_ratio;
        println!(
            "{:<22} {:<6} {:>3} actions: success {}, OSR {:.2}, RDR {:.3}",
            scene.id,
            scene.difficulty.map_or("?", |d| d.name()),
            actions.len(),
            metrics.success,
            metrics.object_success_rate,
            metrics.remaining_distance_ratio
        );
    }
    let n = scenes.len().max(1) as f64;
    println!(
        "expert: SR {:.3}  OSR {:.3}  RDR {:.3}  ({} episodes)",
        f64::from(successes) / n,
        osr / n,
        rdr / n,
        scenes.len()
    );
    Ok(())
}
