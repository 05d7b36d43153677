"""Helpers of the export tests (zarr, Minari, LeRobot): running `esrp demos export`, and records
of episodes played on the real server, as a recording server writes them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import esrp
from esrp.cli import main
from esrp.eval.evaluation import expert_trajectory
from esrp.eval.results import SCHEMA, EpisodeRecord

__all__ = ["export", "played", "record_of", "write_records"]


def export(server: esrp.LocalServer, out: Path, *more: str) -> int:
    return main(["demos", "export", "--server", server.address, "--out", str(out), "--no-progress", *more])


def record_of(
    client: esrp.Client, scene: str, actions: list[int], agent: str, horizon: int = 0
) -> EpisodeRecord:
    """The `esrp.results/v1` record of `actions` stepped on a new (non-privileged) episode of
    `scene`, as a recording server writes it (the actions taken until the episode ended)."""
    info = client.server_info()
    with client.create_episode(scene, horizon=horizon) as episode:
        taken: list[int] = []
        metrics = None
        for action in actions:
            result = episode.step(action)
            taken.append(action)
            if result.ended:
                metrics = result.metrics
                break
        end = "agent" if metrics is None else "success" if metrics.success else "horizon"
        if metrics is None:
            metrics = episode.close()
        summary = episode.scene
    return EpisodeRecord(
        schema=SCHEMA,
        scene_id=scene,
        dataset=info.dataset,
        split="test",
        room_type=summary.room_type,
        difficulty="easy",
        objects=summary.movable_objects,
        agent=agent,
        agent_config={},
        seed=None,
        success=metrics.success,
        osr=metrics.object_success_rate,
        rdr=metrics.remaining_distance_ratio,
        stage=metrics.stage,
        placed=metrics.placed,
        steps=metrics.steps,
        horizon=horizon or summary.horizon,  # the listing says the scene's own
        end=end,
        total_reward=metrics.total_reward,
        actions=taken,
        wall_seconds=1.0,
        agent_stats={},
        server_version=info.version,
        client="test_demos",
        finished_at="2026-11-23T19:40:00Z",
    )


def write_records(path: Path, records: list[EpisodeRecord]) -> Path:
    path.write_text("".join(record.to_json() + "\n" for record in records))
    return path


@pytest.fixture(scope="module")
def played(client: esrp.Client, easy_scenes: list[str]) -> list[EpisodeRecord]:
    """Three records: a person's success (the expert's actions, stepped without privilege), a
    person's episode cut by a short horizon, and a random agent's episode it closed early."""
    with client.create_episode(easy_scenes[0], privileged=True) as episode:
        expert = [int(a) for a in expert_trajectory(episode.privileged_state().scene_json)]
    rng = np.random.default_rng(3)
    records = [
        record_of(client, easy_scenes[0], expert, "human"),
        record_of(client, easy_scenes[1], [int(a) for a in rng.integers(0, 6, 12)], "human", horizon=12),
        record_of(client, easy_scenes[0], [int(a) for a in rng.integers(0, 6, 7)], "random", horizon=30),
    ]
    assert [r.end for r in records] == ["success", "horizon", "agent"]
    return records
