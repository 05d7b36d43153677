//! A random agent on one test scene: connects to a server (or starts a local one), creates an
//! episode, takes seeded random actions until the episode ends, and prints its metrics.
//!
//! ```sh
//! cargo run -p esrp-client --example random_agent                      # starts esrp-server
//! cargo run -p esrp-client --example random_agent -- http://127.0.0.1:50051
//! ```

use esrp_client::{Client, EpisodeOptions, LocalServer, RandomActions, Split};

#[tokio::main]
async fn main() -> Result<(), esrp_client::ClientError> {
    // A server given on the command line, or a local one that lives as long as `_local`.
    let (address, _local) = match std::env::args().nth(1) {
        Some(address) => (address, None),
        None => {
            let local = LocalServer::start::<&str>(None, &[])?;
            (local.address.clone(), Some(local))
        }
    };
    let client = Client::connect(&address).await?;
    let (mut episode, first) = client.create_episode(EpisodeOptions::seeded(Split::Test, 0)).await?;
    let scene = episode.scene().clone();
    println!(
        "scene {} ({}, {} objects, horizon {}): first view {}x{}",
        scene.id,
        scene.room_type,
        scene.movable_objects,
        scene.horizon,
        first.ego_rgb.width(),
        first.ego_rgb.height()
    );
    let mut rejected = 0;
    for action in RandomActions::new(1) {
        let result = episode.step(action).await?;
        rejected += u32::from(!result.info.accepted);
        if let Some(m) = result.metrics.filter(|_| result.ended()) {
            println!(
                "ended after {} steps ({rejected} had no effect): success {}, OSR {:.2}, RDR {:.3}, stage {}, return {:.2}",
                m.steps, m.success, m.object_success_rate, m.remaining_distance_ratio, m.stage, m.total_reward
            );
            break;
        }
    }
    episode.close().await?;
    Ok(())
}
