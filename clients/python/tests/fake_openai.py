"""A fake OpenAI-compatible chat-completions server for the ESRP-VLM tests: the standard library's
`ThreadingHTTPServer` in a thread, answering `POST /v1/chat/completions` from a script (a Python
callable) and keeping every request it got, decoded: the messages, the text and the images (PNG
data URLs decoded to arrays). No model, no network beyond the loopback."""

from __future__ import annotations

import base64
import io
import json
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image


@dataclass
class Request:
    """One chat-completions request as the fake server got it."""

    body: dict[str, Any]
    headers: dict[str, str]
    texts: list[str]  # the text parts of the first user message
    images: list[npt.NDArray[np.uint8]]  # its images, decoded
    pngs: list[bytes]  # and their PNG bytes
    corrections: list[str]  # the text of later user messages (correction requests)
    answers: list[str]  # the assistant messages it carries (earlier answers)

    @property
    def text(self) -> str:
        return "\n".join(self.texts)


@dataclass
class Reply:
    """What the fake server answers: a completion with `content`, an HTTP error `status`, or
    `raw`, a body that is not JSON (`content-type: text/html`), or `body`, any JSON."""

    content: str | None = None
    status: int = 200
    raw: str | None = None
    body: Any = None  # a JSON body answered as it is (with `status`), instead of a completion
    prompt_tokens: int = 100
    completion_tokens: int = 10


def decode(url: str) -> tuple[npt.NDArray[np.uint8], bytes]:
    prefix = "data:image/png;base64,"
    assert url.startswith(prefix), url[:40]
    png = base64.b64decode(url[len(prefix) :])
    with Image.open(io.BytesIO(png)) as image:
        assert image.format == "PNG"
        assert image.mode == "RGB"
        return np.asarray(image).copy(), png


def parse(body: dict[str, Any], headers: dict[str, str]) -> Request:
    messages = body["messages"]
    assert messages[0]["role"] == "system"
    user = messages[1]
    assert user["role"] == "user"
    texts, images, pngs = [], [], []
    for part in user["content"]:
        if part["type"] == "text":
            texts.append(part["text"])
        else:
            assert part["type"] == "image_url"
            array, png = decode(part["image_url"]["url"])
            images.append(array)
            pngs.append(png)
    corrections = [m["content"] for m in messages[2:] if m["role"] == "user"]
    answers = [m["content"] for m in messages[2:] if m["role"] == "assistant"]
    return Request(body, headers, texts, images, pngs, corrections, answers)


@dataclass
class Json:
    """A scripted JSON body (which may be a string: not the HTML page a `str` payload is)."""

    value: Any


Script = Callable[[Request], Reply]


@dataclass
class FakeServer:
    """The running fake: its base URL, the requests it got, and the most it had in flight at once."""

    base_url: str
    script: Script
    requests: list[Request] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)  # script errors (a check that failed)
    in_flight: int = 0
    most_in_flight: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def handle(self, body: dict[str, Any], headers: dict[str, str]) -> tuple[int, Any]:
        with self.lock:
            self.in_flight += 1
            self.most_in_flight = max(self.most_in_flight, self.in_flight)
        try:
            request = parse(body, headers)
            with self.lock:
                self.requests.append(request)
            reply = self.script(request)
        except Exception as error:  # noqa: BLE001 - reported by the test, answered as a 400 (not retried)
            with self.lock:
                self.failures.append(f"{type(error).__name__}: {error}")
            return 400, {"error": {"message": str(error), "type": "invalid_request_error"}}
        finally:
            with self.lock:
                self.in_flight -= 1
        if reply.raw is not None:
            return reply.status, reply.raw
        if reply.body is not None:
            return reply.status, Json(reply.body)
        if reply.status != 200:
            return reply.status, {"error": {"message": f"scripted {reply.status}", "type": "server_error"}}
        return 200, {
            "id": f"chatcmpl-{len(self.requests)}",
            "object": "chat.completion",
            "created": 0,
            "model": body.get("model", "fake"),
            "choices": [
                {
                    "index": 0,
                    "message": {"role": "assistant", "content": reply.content},
                    "finish_reason": "stop",
                }
            ],
            "usage": {
                "prompt_tokens": reply.prompt_tokens,
                "completion_tokens": reply.completion_tokens,
                "total_tokens": reply.prompt_tokens + reply.completion_tokens,
            },
        }


@contextmanager
def fake_openai(script: Script) -> Iterator[FakeServer]:
    """Runs a fake server answering from `script` on a free loopback port until the block ends."""
    fake = FakeServer("", script)

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def do_POST(self) -> None:  # noqa: N802 - the http.server name
            length = int(self.headers.get("content-length", "0"))
            body = json.loads(self.rfile.read(length))
            payload: Any
            if self.path.rstrip("/") != "/v1/chat/completions":
                status, payload = 404, {"error": {"message": f"no route {self.path}"}}
            else:
                status, payload = fake.handle(body, {k.lower(): v for k, v in self.headers.items()})
            html = isinstance(payload, str)
            if isinstance(payload, Json):
                payload = payload.value
            data = (payload if html else json.dumps(payload)).encode()
            self.send_response(status)
            self.send_header("content-type", "text/html" if html else "application/json")
            self.send_header("content-length", str(len(data)))
            # The openai client honours this delay before retrying a 429 or 5xx: keeps the tests fast.
            self.send_header("retry-after-ms", "5")
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002, ANN401
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    fake.base_url = f"http://127.0.0.1:{server.server_address[1]}/v1"
    thread = threading.Thread(target=server.serve_forever, name="fake-openai", daemon=True)
    thread.start()
    try:
        yield fake
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
