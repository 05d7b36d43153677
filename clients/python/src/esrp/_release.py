"""Which esrp package and esrp-server versions work together (no imports: the CLI's start-up and
`esrp doctor` use it without loading gRPC).
"""

from __future__ import annotations

__all__ = ["same_release"]


def same_release(client: str, server: str) -> bool:
    """Whether a client and a server version speak to each other: the same major and minor version
    (`0.1.0` and `0.1.3` do; `0.1.0` and `0.2.0` do not).
    """
    return client.split(".")[:2] == server.split(".")[:2]
