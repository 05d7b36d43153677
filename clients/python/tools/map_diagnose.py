"""Why ESRP-MAP fails where it fails: plays the agent on privileged episodes (the agent itself sees
only its observations, as under `esrp eval`; the privileged state is read by this tool alone) and
compares what the agent believed with the truth.

    python clients/python/tools/map_diagnose.py --split test --difficulty easy --limit 30 \
        --images runs/map-diag --out runs/map-diag.jsonl

For each episode: its outcome, the registration's error against the goal frame computed from the
privileged geometry (heading, scale, the start position in goal pixels; the first registration and
the last), each object's final IoU
and placement, the agent's statistics, and a reason for a failure, the first that applies:

- `registration`: the heading is wrong, the scale off by more than 4 % or the start position by
  more than 2 goal pixels;
- `not-found`: it gave up, or ran out of steps, while looking for an object (never fetched one it
  wanted);
- `carry`: it gave up, or ran out of steps, holding an object (no way found, or stuck on contacts);
- `placement`: it released an object with an IoU under the threshold;
- `fetch`: it drove to an object and its fetches failed;
- `other`: none of these.

`--images DIR` writes the agent's debug image (`MapAgent.debug_image`) at the end of each failed
episode, with the true targets' centres drawn in cyan and the objects' true positions in orange.
With `--phases` as well, it also writes one at every change of the agent's phase, of every episode
(`SCENE-stepNNN-PHASE.png`: registered and about to fetch, holding the object with its carry plan,
...), the truth drawn as at the end.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import esrp
from esrp.agents.esrp_map.agent import MapAgent
from esrp.agents.esrp_map.goal import TOP_DOWN_MARGIN
from esrp.agents.esrp_map.planner import HeldObject
from esrp.agents.esrp_map.register import Registration


def goal_frame(state: esrp.PrivilegedState, resolution: int) -> tuple[float, float, float]:
    """esrp-render's TopDownFrame from the privileged geometry: (min_x, min_z, metres per pixel)."""
    xs = [x for x, _ in state.floor]
    zs = [z for _, z in state.floor]
    for static in state.static_obstacles:
        if static.obstacle.kind == "wall":
            f = static.footprint
            c, s = math.cos(f.yaw), math.sin(f.yaw)
            for sx, sz in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                lx, lz = sx * f.half_x, sz * f.half_z
                xs.append(f.center_x + lx * c + lz * s)
                zs.append(f.center_z - lx * s + lz * c)
    side = max(max(xs) - min(xs), max(zs) - min(zs)) + 2 * TOP_DOWN_MARGIN
    centre = ((min(xs) + max(xs)) / 2, (min(zs) + max(zs)) / 2)
    return centre[0] - side / 2, centre[1] - side / 2, side / resolution


def fit_error(
    fit: Registration, start: esrp.PrivilegedState, frame: tuple[float, float, float]
) -> dict[str, Any]:
    """How far registration `fit` is from the truth: its heading's error (lattice steps), its
    scale's (relative) and the start position's in goal pixels."""
    min_x, min_z, metres = frame
    col = (start.agent_x - min_x) / metres
    row = (start.agent_z - min_z) / metres
    return {
        "heading": fit.heading - start.agent_heading,
        "scale": round(float(fit.scale * metres - 1), 4),
        "pixels": round(math.hypot(fit.tx - col, fit.tz - row), 2),
    }


def held_truth(agent: MapAgent, start: esrp.PrivilegedState, now: esrp.PrivilegedState) -> HeldObject | None:
    """The held object's footprint relative to the agent's believed pose, from the privileged state."""
    if now.held is None:
        return None
    f = now.objects[now.held].footprint
    y0 = start.agent_yaw
    dx, dz = f.center_x - start.agent_x, f.center_z - start.agent_z
    # World → the agent's start frame, then → relative to its believed pose.
    x = dx * math.cos(y0) - dz * math.sin(y0)
    z = dx * math.sin(y0) + dz * math.cos(y0)
    s = agent.state
    ahead = (x - s.x) * math.cos(s.yaw) - (z - s.z) * math.sin(s.yaw)
    right = (x - s.x) * math.sin(s.yaw) + (z - s.z) * math.cos(s.yaw)
    return HeldObject(ahead, right, f.yaw - y0 - s.yaw, f.half_x, f.half_z)


def held_error(estimate: HeldObject, truth: HeldObject) -> dict[str, float]:
    """How far the agent's belief of the held object is from the truth: centre (metres), yaw
    (degrees, modulo a half turn), and size (metres, the larger half size's error)."""
    if truth.half_x < truth.half_z:  # the agent's half_x is the long side: compare like with like
        truth = HeldObject(truth.ahead, truth.right, truth.rel_yaw + math.pi / 2, truth.half_z, truth.half_x)
    yaw = math.degrees((estimate.rel_yaw - truth.rel_yaw) % math.pi)
    yaw = min(yaw, 180 - yaw)
    # The half sizes may be swapped with the yaw a quarter turn off: compare the long sides.
    return {
        "centre": round(math.hypot(estimate.ahead - truth.ahead, estimate.right - truth.right), 3),
        "yaw": round(yaw if yaw <= 90 else 180 - yaw, 1),
        "size": round(max(estimate.half_x, estimate.half_z) - max(truth.half_x, truth.half_z), 3),
    }


def play(
    client: esrp.Client, scene: str, images: Path | None, oracle: bool = False, phases: bool = False
) -> dict[str, Any]:
    """One episode of the agent on `scene`, diagnosed. With `oracle`, the agent's belief of a held
    object is replaced by the truth after each fetch (what a perfect estimate would give). With
    `phases` (and `images`), the debug image at every change of the agent's phase is saved too."""
    agent = MapAgent()
    started = time.perf_counter()
    with client.create_episode(scene, privileged=True) as episode:
        observation = episode.observation
        assert observation is not None
        assert observation.goal_rgb is not None
        start = episode.privileged_state()
        frame = goal_frame(start, observation.goal_rgb.shape[0])
        agent.reset(observation, {})
        steps, ended_by = 0, "agent"
        registration_error: dict[str, Any] | None = None
        held_errors: list[dict[str, float]] = []
        seen_held: HeldObject | None = None
        phase = agent._phase
        while True:
            action = agent.act(observation)
            if phases and images is not None and agent._phase != phase:
                phase = agent._phase
                name = f"{scene.replace('/', '-')}-step{steps:03d}-{phase}.png"
                save_image(agent, episode.privileged_state(), frame, images / name)
            if agent._held is not None and agent._held is not seen_held:
                truth = held_truth(agent, start, episode.privileged_state())
                if truth is not None:
                    held_errors.append(held_error(agent._held, truth))
                    if oracle:
                        agent._held = truth
                        agent._plan = []  # the next step replans with the truth
                seen_held = agent._held
            if registration_error is None and agent.registration is not None:
                registration_error = fit_error(agent.registration, start, frame)
            if action is None:
                break
            result = episode.step(action)
            steps += 1
            observation = result.observation
            if result.terminated or result.truncated:
                ended_by = "success" if result.terminated else "horizon"
                break
        final = episode.privileged_state()
    last = agent.registration
    stats = agent.stats()
    success = ended_by == "success"
    record: dict[str, Any] = {
        "scene": scene,
        "success": success,
        "steps": steps,
        "ended_by": ended_by,
        "registration": registration_error,
        "last_registration": None if last is None else fit_error(last, start, frame),
        "held": held_errors,
        "objects": [
            {"category": o.category, "iou": round(o.iou, 3), "placed": o.placed, "held": o.held}
            for o in final.objects
        ],
        "stats": stats,
        "seconds": round(time.perf_counter() - started, 1),
    }
    record["reason"] = None if success else reason(record, stats)
    if images is not None and not success:
        save_image(agent, final, frame, images / f"{scene.replace('/', '-')}.png")
    return record


def reason(record: dict[str, Any], stats: dict[str, Any]) -> str:
    """The first explanation of a failure that applies (see the module)."""
    error = record["registration"]
    if error is None or error["heading"] != 0 or abs(error["scale"]) > 0.04 or error["pixels"] > 2.0:
        return "registration"
    phase = stats.get("phase")
    if any(o["held"] for o in record["objects"]) or phase == "carry":
        return "carry"
    if phase in ("explore", "wander", "look") or (phase == "fetch" and stats.get("fetches", 0) == 0):
        return "not-found"
    if stats.get("releases", 0) > 0 and not all(o["placed"] for o in record["objects"]):
        return "placement"
    if phase in ("fetch", "fetching"):
        return "fetch"
    return "other"


def save_image(
    agent: MapAgent, state: esrp.PrivilegedState, frame: tuple[float, float, float], path: Path
) -> None:
    """The agent's debug image with the truth drawn on it."""
    from PIL import Image

    scale = 4
    image = agent.debug_image(scale=scale).copy()
    min_x, min_z, metres = frame
    side = image.shape[0]

    def dot(x: float, z: float, colour: tuple[int, int, int]) -> None:
        c = int((x - min_x) / metres * scale)
        r = int((z - min_z) / metres * scale)
        image[max(r - 3, 0) : min(r + 3, side), max(c - 3, 0) : min(c + 3, side)] = colour

    for o in state.objects:
        dot(o.target_footprint.center_x, o.target_footprint.center_z, (0, 230, 230))
        dot(o.footprint.center_x, o.footprint.center_z, (255, 140, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(image)).save(path)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--split", default="test")
    parser.add_argument("--difficulty", default="easy")
    parser.add_argument("--offset", type=int, default=0)
    parser.add_argument("--limit", type=int, default=30)
    parser.add_argument("--scenes", default=None, help="comma-separated scene ids (instead of the listing)")
    parser.add_argument("--images", type=Path, default=None, help="folder for failed episodes' debug images")
    parser.add_argument("--out", type=Path, default=None, help="JSON lines, one per episode")
    parser.add_argument("--server-binary", type=Path, default=None)
    parser.add_argument(
        "--oracle-held",
        action="store_true",
        help="give the agent the held object's true footprint after each fetch",
    )
    parser.add_argument(
        "--phases",
        action="store_true",
        help="with --images: also an image at every change of the agent's phase, in every episode",
    )
    args = parser.parse_args()
    with esrp.LocalServer(binary=args.server_binary) as server:
        client = esrp.Client(server.address)
        if args.scenes:
            scenes = args.scenes.split(",")
        else:
            listing = list(client.scenes(args.split, args.difficulty, page_size=1000))
            scenes = [s.id for s in listing[args.offset : args.offset + args.limit]]
        out = open(args.out, "w") if args.out else None  # noqa: SIM115
        reasons: dict[str, int] = {}
        wins = 0
        for index, scene in enumerate(scenes, 1):
            record = play(client, scene, args.images, args.oracle_held, args.phases)
            wins += record["success"]
            if record["reason"]:
                reasons[record["reason"]] = reasons.get(record["reason"], 0) + 1
            if out:
                out.write(json.dumps(record) + "\n")
                out.flush()
            print(
                f"{index}/{len(scenes)} {scene} {'OK ' if record['success'] else 'FAIL'} "
                f"{record['reason'] or ''} steps {record['steps']} reg {record['registration']} "
                f"ious {[o['iou'] for o in record['objects']]} held {record['held']} stats {record['stats']}",
                flush=True,
            )
        print(f"SR {wins}/{len(scenes)}; failures by reason: {reasons}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
