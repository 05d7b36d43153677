"""Writes the seed corpora of the request fuzz targets (fuzz/seeds/esrp_v1_requests and
fuzz/seeds/dm_env_requests): real requests of both APIs, encoded as the server receives them,
with the real scenes of fuzz/seeds/scene_json as CreateEpisode's inline scene JSON.

Run from the repository root with the venv that scripts/python-tests.sh makes (it has the
esrp package's esrp.v1 stubs and dm_env_rpc): `.venv/bin/python fuzz/tools/make_seeds.py`.
esrp_v1_requests reads its first byte as the request kind (0 CreateEpisode, 1 Step, 2 StepBatch,
3 Reset, 4 PlanActions) and the rest as that message.
"""

from __future__ import annotations

from pathlib import Path

from dm_env_rpc.v1 import dm_env_rpc_pb2 as dm
from dm_env_rpc.v1 import tensor_utils
from esrp.v1 import esrp_pb2 as pb

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "seeds" / "scene_json").glob("*.json"))


def write(target: str, name: str, data: bytes) -> None:
    folder = ROOT / "seeds" / target
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(data)


def esrp_v1() -> None:
    kind = {"create": 0, "step": 1, "batch": 2, "reset": 3, "plan": 4}

    def put(name: str, message_kind: str, message: object) -> None:
        write("esrp_v1_requests", name, bytes([kind[message_kind]]) + message.SerializeToString())  # type: ignore[attr-defined]

    put("create-scene-id", "create", pb.CreateEpisodeRequest(scene_id="esrp-bench-v2/00003", seed=7))
    put("create-split", "create", pb.CreateEpisodeRequest(split=pb.SPLIT_TEST, horizon=300))
    put(
        "create-sensors-reward",
        "create",
        pb.CreateEpisodeRequest(
            scene_id="esrp-bench-v2/00000",
            sensors=pb.Sensors(ego_depth=True, ego_segmentation=True, current_top_down=True, resolution=256),
            reward=pb.RewardWeights(success=10.0, place=1.0, unplace=-1.0, potential=0.1, holding=0.0, living=-0.01),
            privileged=True,
        ),
    )
    for scene in SCENES:
        put(f"create-json-{scene.stem}", "create", pb.CreateEpisodeRequest(scene_json=scene.read_text()))
    put("step", "step", pb.StepRequest(episode_id="0f1e2d3c4b5a69788796a5b4c3d2e1f0", action=4, include_goal=True))
    steps = [pb.StepRequest(episode_id=f"episode-{i}", action=i % 6) for i in range(8)]
    put("batch", "batch", pb.StepBatchRequest(steps=steps))
    put("batch-duplicate", "batch", pb.StepBatchRequest(steps=[steps[0], steps[0]]))
    put("reset", "reset", pb.ResetRequest(episode_id="episode-0"))
    put("reset-scene", "reset", pb.ResetRequest(episode_id="episode-0", scene_id="esrp-bench-v2/00001"))
    put("reset-json", "reset", pb.ResetRequest(episode_id="episode-0", scene_json=SCENES[0].read_text()))
    put("plan", "plan", pb.PlanActionsRequest(episode_id="episode-0", max_actions=20, budget_ms=500))


def dm_env() -> None:
    def put(name: str, request: dm.EnvironmentRequest) -> None:
        write("dm_env_requests", name, request.SerializeToString())

    def settings(**values: object) -> dict[str, dm.Tensor]:
        return {key: tensor_utils.pack_tensor(value) for key, value in values.items()}

    create = dm.CreateWorldRequest(
        settings=settings(scene="esrp-bench-v2/00002", seed=3, horizon=250, resolution=64, ego_depth=True)
    )
    put("create-world", dm.EnvironmentRequest(create_world=create))
    split = dm.CreateWorldRequest(settings=settings(split="test", current_top_down=True, ego_segmentation=False))
    put("create-world-split", dm.EnvironmentRequest(create_world=split))
    put("join-world", dm.EnvironmentRequest(join_world=dm.JoinWorldRequest(world_name="world-0")))
    step = dm.StepRequest(actions={1: tensor_utils.pack_tensor(2)}, requested_observations=[1, 2, 3])
    put("step", dm.EnvironmentRequest(step=step))
    put("reset", dm.EnvironmentRequest(reset=dm.ResetRequest()))
    reset_world = dm.ResetWorldRequest(world_name="world-0", settings=settings(scene="esrp-bench-v2/00000"))
    put("reset-world", dm.EnvironmentRequest(reset_world=reset_world))
    put("destroy-world", dm.EnvironmentRequest(destroy_world=dm.DestroyWorldRequest(world_name="world-0")))


if __name__ == "__main__":
    esrp_v1()
    dm_env()
    for target in ("esrp_v1_requests", "dm_env_requests"):
        print(target, len(list((ROOT / "seeds" / target).iterdir())), "seeds")
