"""Agents for `esrp eval`: the `Agent` protocol (and its asyncio twin `AsyncAgent`), the uniform
`RandomAgent`, and `load_factory`, which turns `--agent MODULE:CALLABLE` into a factory.

An agent plays one episode at a time: `reset(observation, info)` at the start, then `act(observation)`
after each step, until the episode ends (success or the horizon) or `act` returns None (the agent
stops; the record's `end` is `"agent"`). Every observation it is given carries the goal image
(`observation.goal_rgb`). `esrp eval` makes one agent per episode by calling the factory with the
agent configuration, so instances never see two episodes at once:

    factory(config: dict[str, Any]) -> Agent | AsyncAgent

`config` is `--agent-config` (a JSON object, `{}` by default); it is recorded as `agent_config`.
An agent may define `stats() -> dict` (recorded as `agent_stats` at the end of its episode, as JSON
carries it: numpy values as numbers and lists, NaN and infinities as null).

The same agents play the Gymnasium env (`esrp/Rearrange-v1`) through `as_observation`, which
makes the env's observation dict an `Observation` (no copy):

    observation, info = env.reset(options={"scene": scene})
    agent.reset(as_observation(observation), info)
    while (action := agent.act(as_observation(observation))) is not None:
        observation, reward, terminated, truncated, info = env.step(int(action))
        if terminated or truncated:
            break
"""

from __future__ import annotations

import importlib
import inspect
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol, cast, runtime_checkable

import numpy as np

from .._values import Action, Observation
from ._config import check_agent_config

__all__ = [
    "Agent",
    "AgentFactory",
    "AsyncAgent",
    "RandomAgent",
    "as_observation",
    "load_factory",
    "raised_at",
]


@runtime_checkable
class Agent(Protocol):
    """An agent whose calls return at once (or block: they run on the evaluation's event loop, so a
    slow one holds up every other episode; make a slow agent an `AsyncAgent`).
    """

    def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode.

        Args:
            observation: The first observation (`ego_rgb`, `goal_rgb`, `grasping`, the sensors).
            info: `scene_id`, `room_type`, `difficulty`, `objects` (movable objects), `horizon`,
                `split`, `seed` (the per-scene seed: draw your random numbers from it),
                `episode_id`.
        """

    def act(self, observation: Observation) -> Action | int | None:
        """The next action (an `Action` or its code 0..5), or None to stop the episode here."""


@runtime_checkable
class AsyncAgent(Protocol):
    """The asyncio twin of `Agent`, for agents that wait on a model (a server, a GPU queue): while one
    episode's agent awaits, the other episodes go on.
    """

    async def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Starts an episode (as `Agent.reset`)."""

    async def act(self, observation: Observation) -> Action | int | None:
        """The next action, or None to stop (as `Agent.act`)."""


def as_observation(observation: Mapping[str, Any]) -> Observation:
    """The Gymnasium env's observation dict (`ego_rgb`, `goal_rgb`, `grasping` and the sensors it
    was made with) as the `Observation` an agent is given, sharing its arrays.
    """
    missing = {"ego_rgb", "grasping"} - set(observation)
    if missing:
        raise ValueError(f"not an esrp observation: it lacks {sorted(missing)}")
    return Observation(
        ego_rgb=observation["ego_rgb"],
        grasping=bool(observation["grasping"]),
        goal_rgb=observation.get("goal_rgb"),
        depth=observation.get("depth"),
        segmentation=observation.get("segmentation"),
        current_top_down=observation.get("current_top_down"),
    )


AgentFactory = Callable[[dict[str, Any]], "Agent | AsyncAgent"]
"""What `--agent MODULE:CALLABLE` names: called with the agent config, once per episode.

A factory may name, in an attribute `settings_free_on_resume` (a set of str), the settings of its
config that change how it runs but not what it plays (timeouts, concurrency, where logs go):
`esrp eval` resumes a results file whose records differ from the run's config only in those.
"""


class RandomAgent:
    """Uniform random actions, seeded per episode.

    Its generator is numpy's `default_rng(info["seed"])` (PCG64), one `integers(0, 6)` per step: the
    same seed gives the same actions, on any machine. (The Rust `esrp-eval` draws from ChaCha8, so
    the two tools' random agents play different action streams from the same seed.) It has no
    settings: a config with any key raises `ValueError`.
    """

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        check_agent_config(config or {}, "random", {})
        self.config = dict(config or {})
        self._rng = np.random.default_rng(0)

    def reset(self, observation: Observation, info: Mapping[str, Any]) -> None:
        """Seeds the generator with the episode's seed."""
        self._rng = np.random.default_rng(int(info["seed"]))

    def act(self, observation: Observation) -> Action:
        """A uniform random action."""
        return Action(int(self._rng.integers(0, 6)))


def is_async_agent(agent: object) -> bool:
    """Whether `agent`'s `act` is a coroutine function (an `AsyncAgent`)."""
    return inspect.iscoroutinefunction(getattr(agent, "act", None))


def raised_at(error: BaseException) -> str:
    """` (file.py:line)`: where `error` was raised, or nothing when that is unknown or when its
    own message says it (a SyntaxError's: `invalid syntax (file.py, line 2)`).
    """
    if isinstance(error, SyntaxError):
        return ""
    frames = traceback.extract_tb(error.__traceback__)
    return f" ({Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""


def _names_module(error: ImportError, module_name: str) -> bool:
    """Whether `error` says that `module_name` itself (or a package it is in) is not there, rather
    than that something the module imports is missing.
    """
    if not isinstance(error, ModuleNotFoundError) or error.name is None:
        return False
    return module_name == error.name or module_name.startswith(error.name + ".")


def load_factory(spec: str) -> AgentFactory:
    """The callable named by `MODULE:CALLABLE` (e.g. `my_agents:make_agent`, `pkg.mod:Agent`): the
    module is imported (the working directory is on the path when `esrp` runs), and CALLABLE may be
    dotted (`module:Class.create`). Raises `ValueError` saying what is missing, or what importing
    the module raised (and where).
    """
    module_name, sep, attribute = spec.partition(":")
    if not sep or not module_name or not attribute:
        raise ValueError(
            f"agent {spec!r} is none of random, expert, plan, vlm, bc, ppo, map, nor MODULE:CALLABLE "
            "(a factory of agents, e.g. my_agents:make_agent)"
        )
    try:
        target: Any = importlib.import_module(module_name)
    except ImportError as error:
        if not _names_module(error, module_name):
            # The module was found but an import in it failed (a missing dependency): say where.
            raise ValueError(
                f"importing {module_name!r} for agent {spec!r} raised {type(error).__name__}: {error}"
                f"{raised_at(error)}"
            ) from error
        raise ValueError(f"cannot import {module_name!r} for agent {spec!r}: {error}") from error
    except Exception as error:  # noqa: BLE001 - the user's module: said in one line, with its place.
        raise ValueError(
            f"importing {module_name!r} for agent {spec!r} raised {type(error).__name__}: {error}"
            f"{raised_at(error)}"
        ) from error
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise ValueError(f"{module_name!r} has no {attribute!r} (agent {spec!r})")
        target = getattr(target, part)
    if not callable(target):
        raise ValueError(f"{spec!r} is not callable: it must be a factory called with the agent config")
    return cast("AgentFactory", target)
