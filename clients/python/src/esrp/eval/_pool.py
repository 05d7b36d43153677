"""The worker pool of `esrp eval` and `esrp verify`: a few asyncio tasks that share one queue of
episodes, run together on one event loop, and stop together when one of them fails.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from typing import Any

__all__ = ["run_workers"]


async def run_workers(count: int, worker: Callable[[], Coroutine[Any, Any, None]]) -> None:
    """Runs `count` tasks of `worker()` (none when `count` is 0) until all have returned. When one
    raises, or the wait is cancelled (a signal), the others are cancelled and awaited before the
    error goes on: no worker outlives the call, so what the workers share (an open results file, a
    progress bar) may be closed right after it.
    """
    tasks = [asyncio.ensure_future(worker()) for _ in range(count)]
    try:
        await asyncio.gather(*tasks)
    except BaseException:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        raise
