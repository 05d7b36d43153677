"""The Gymnasium id `esrp/Rearrange-v1` and its registration (the `gym` extra).

The entry points are strings, so registering imports neither `esrp.envs` nor anything it needs;
`gymnasium.make` imports `esrp.envs` when an env is made. Registering does import gymnasium, which
sets `PYGAME_HIDE_SUPPORT_PROMPT` on import; so `import esrp` registers only where gymnasium is
imported already, and importing `esrp.envs` registers always.
"""

from __future__ import annotations

import importlib.util
import sys

ENV_ID = "esrp/Rearrange-v1"
"""The Gymnasium id of the ESRP environment (`gymnasium.make` and `gymnasium.make_vec`)."""


def register_envs() -> None:
    """Registers `ENV_ID` with gymnasium (once), when gymnasium is installed."""
    if importlib.util.find_spec("gymnasium") is None:
        return
    from gymnasium.envs.registration import register, registry

    if ENV_ID not in registry:
        register(
            id=ENV_ID,
            entry_point="esrp.envs:RearrangeEnv",
            vector_entry_point="esrp.envs:RearrangeVectorEnv",
        )


def register_if_gymnasium_is_loaded() -> None:
    """`register_envs`, where gymnasium was imported already (it changes nothing then)."""
    if "gymnasium" in sys.modules:
        register_envs()
