"""A real OpenAI-compatible chat-completions server on 127.0.0.1 for the tests.

Its replies are computed from the images it receives: it decodes the current depth PNG
from the request, chooses as the geometric pilot would, and phrases the answer the way
models do (reasoning first, fenced or inline, single or double quotes, varied wording).
Faults can be queued per request or switched on for good to exercise the failure paths:
wrong replies, HTTP errors, a proxy's HTML page, a slow answer, a reply dripped one
byte at a time (headers at once, then a byte every `drip_s`), and careless servers that
echo the request's API key back (in an error body, a page or a reply). `GET /models` can
be made to answer with something that is no model list (`models_answer`).
"""

from __future__ import annotations

import base64
import io
import json
import math
import re
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
from PIL import Image

from cavenav.core.types import Action, Observation
from cavenav.pilots.geometric import GeometricPilot

FAULTS = (
    "garbage", "two_keys", "out_of_set", "429", "500", "slow", "401", "html", "drip",
    "echo_key_500", "echo_key_html", "echo_key_reply",
)  # fmt: skip

# What a proxy in front of a model server sends when the server is down: a 200 with a page,
# longer than what a run folder keeps of it.
PROXY_PAGE = (
    "<!DOCTYPE html><html><head><title>Service temporarily unavailable</title></head><body>"
    + "<p>The upstream server did not answer; please try again later.</p>" * 60
    + "</body></html>"
)


def _decode(url: str, mode: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert(mode))


def _phrase(action: Action, style: int) -> str:
    """The action in one of several wordings a model might use."""
    parts = []
    if action.forward:
        word = ("forward", "ahead", "move forward")[style % 3] if action.forward > 0 else "back"
        unit = ("m", "meters", "metres")[style % 3]
        parts.append(f"{word} {abs(action.forward):g} {unit}")
    if action.right:
        side = "right" if action.right > 0 else "left"
        parts.append(f"{('strafe', 'shift', 'move')[style % 3]} {side} {abs(action.right):g} m")
    if action.up:
        word = (
            ("ascend", "up", "rise")[style % 3]
            if action.up > 0
            else ("descend", "down", "sink")[style % 3]
        )
        parts.append(f"{word} {abs(action.up):g}m")
    if action.yaw_deg:
        side = "left" if action.yaw_deg > 0 else "right"
        unit = ("deg", "degrees", "°")[style % 3]
        verb = ("turn", "yaw", "rotate")[style % 3]
        parts.append(f"{verb} {side} {abs(action.yaw_deg):g}{'' if unit == '°' else ' '}{unit}")
    if not parts:
        return ("hold", "Hold", "stay")[style % 3]
    if style % 2:
        parts.reverse()
    return (", ", " + ", " and ")[style % 3].join(parts)


def _reply(action: Action, justification: str, style: int) -> str:
    text = _phrase(action, style)
    reasoning = (
        "Let me think step by step.\n(a) Situation: "
        + justification.split("Constraints:")[0]
        + "\n(b) Constraints: "
        + justification.split("Constraints:")[-1].split("Choice:")[0]
        + "\n(c) Action: I choose the motion below."
    )
    if style % 3 == 0:
        return f"{reasoning}\n\n```json\n{json.dumps({text: justification})}\n```"
    if style % 3 == 1:
        quoted = justification.replace("'", "")
        return f"{reasoning}\nFinal answer: {{'{text}': '{quoted}'}}\nI will re-assess then."
    return f'**Reasoning**\n{reasoning}\n\n{{"{text}": "{justification}"}}'


def _design(system: str) -> str:
    """The design a system prompt asks for (`cavenav.pilots.prompts`)."""
    if "# The numbered arrows" in system:
        return "arrows"
    return "waypoint" if "# Your waypoint" in system else "direct"


_OFFER = re.compile(
    r"(\d+) = (?:turn (left|right) [\d.]+ degrees in place|"
    r"(?:(\d+) degrees (left|right))?(?:, )?(?:(\d+) degrees (up|down))?(?:straight ahead)?, "
    r"([\d.]+) m free)"
)


Offered = tuple[int, float, float, float]  # number, bearing, elevation, free metres


def _offered(text: str) -> list[Offered]:
    """The numbers a request offers: (number, bearing, elevation, free metres; 0 for a
    turn in place), degrees, left and up positive."""
    offered = []
    for m in _OFFER.finditer(text):
        number, turn, bearing, side, elevation, updown, free = m.groups()
        if turn:
            offered.append((int(number), 45.0 if turn == "left" else -45.0, 0.0, 0.0))
            continue
        b = float(bearing or 0) * (1 if side == "left" else -1)
        e = float(elevation or 0) * (1 if updown == "up" else -1)
        offered.append((int(number), b, e, float(free)))
    return offered


def _choose(
    action: Action, offered: list[Offered], design: str, shape: tuple[int, int], style: int
) -> str:
    """The offered number (or, every other waypoint, its point) nearest the geometric
    pilot's heading. Where that pilot would turn away out of view, an arrow that way
    reaching 8 m or more, else the turn in place."""
    ahead = [o for o in offered if o[3]]
    if not action.forward and abs(action.yaw_deg) >= 26.5:
        side = 1.0 if action.yaw_deg > 0 else -1.0
        ahead = [o for o in ahead if o[1] * side > 0 and o[3] >= 8.0]
    if not ahead:
        turns = [o for o in offered if not o[3] and (o[1] > 0) == (action.yaw_deg >= 0)]
        return str(turns[0][0])
    number, bearing, elevation, _ = min(ahead, key=lambda o: abs(o[1] - action.yaw_deg))
    if design == "arrows":
        up = round(action.up, 2)
        if up:
            return f"{number}, {'ascend' if up > 0 else 'descend'} {abs(up):g} m"
        return str(number)
    if style % 2:
        h, w = shape
        focal = 0.5 * w / math.tan(math.radians(53.13) / 2)
        b, e = math.radians(bearing), math.radians(elevation)
        x = (0.5 * w - focal * math.tan(b)) / w
        y = (0.5 * h - focal * math.tan(e) / math.cos(b)) / h
        return f"point {x:.3f}, {y:.3f}"
    return str(number)


def _reply_choice(choice: str, justification: str, style: int) -> str:
    reasoning = (
        f"Let me think step by step.\n(a) Situation: {justification}\n(c) I choose {choice}."
    )
    if style % 2:
        return f"{reasoning}\n{{'{choice}': '{justification.replace(chr(39), '')}'}}"
    return f"{reasoning}\n```json\n{json.dumps({choice: justification})}\n```"


class FakeVLM:
    """Owns the server thread; use as a context manager."""

    def __init__(self, required_key: str | None = None):
        self.faults: deque[str] = deque()
        self.persistent_fault: str | None = None
        self.required_key = required_key
        self.requests: list[dict] = []
        # What GET /models answers instead of the model list, as (content type, body).
        self.models_answer: tuple[str, str] | None = None
        self.slow_s = 1.5
        self.drip_s = 2.0
        self._stopped = threading.Event()  # ends replies still dripping
        self._pilot = GeometricPilot()
        self._last_answer: tuple[str, str] | None = None
        self._style = 0
        self._lock = threading.Lock()
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self._server.server_address[1]}/v1"

    def __enter__(self) -> FakeVLM:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stopped.set()
        self._server.shutdown()
        self._server.server_close()

    def answer(self, body: dict) -> str:
        """The reply text for a chat request (the geometric pilot's choice, phrased; in
        the arrows and waypoint designs, the offered number or point nearest it)."""
        messages = body["messages"]
        fresh = messages[-1]["role"] == "user" and isinstance(messages[-1]["content"], list)
        design = _design(messages[0]["content"])
        if fresh or self._last_answer is None:
            content = messages[1]["content"]
            images = [p["image_url"]["url"] for p in content if p["type"] == "image_url"]
            texts = [p["text"] for p in content if p["type"] == "text"]
            current = next(t for t in reversed(texts) if t.startswith("Current observation"))
            top, bottom = (float(v) for v in re.findall(r"= ([-\d.]+) m", current)[:2])
            depth = _decode(images[-1], "L")
            # The server's "model" reads the images with the simulator's camera.
            obs = Observation(
                _decode(images[-2], "RGB"),
                depth.astype(np.float32),
                depth,
                top,
                bottom,
                depth_range=(0.0, 20.0),
                hfov_deg=53.13,
                camera_offset_m=0.2,
            )
            # A designed pilot is asked at some steps only, and flies its own moves in
            # between: a pilot with no memory of earlier requests reads each one.
            remembers = "No earlier observations" not in messages[0]["content"]
            if remembers and not any(t.startswith("Earlier observation") for t in texts):
                self._pilot.reset()  # an episode's first request: nothing seen before
            pilot = self._pilot if design == "direct" else GeometricPilot()
            decision = pilot.decide(obs)
            self._last_answer = (decision.action, decision.justification)
            if design != "direct":
                offered = _offered(texts[-2])
                self._last_answer = (
                    _choose(decision.action, offered, design, depth.shape, self._style),
                    decision.justification,
                )
        self._style += 1
        action, justification = self._last_answer
        if isinstance(action, str):
            return _reply_choice(action, justification, self._style)
        return _reply(action, justification, self._style)

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:  # keep test output clean
                pass

            def _send(
                self,
                status: int,
                payload: dict | str,
                headers: dict | None = None,
                drip: bool = False,
                content_type: str | None = None,
            ) -> None:
                """A JSON payload (or a page, given as text); ``drip``: the body one byte
                every `drip_s`, until the client hangs up or the server stops."""
                html = isinstance(payload, str)
                data = (payload if html else json.dumps(payload)).encode()
                self.send_response(status)
                kind = content_type or ("text/html" if html else "application/json")
                self.send_header("content-type", kind)
                self.send_header("content-length", str(len(data)))
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.end_headers()
                if not drip:
                    self.wfile.write(data)
                    return
                try:
                    for k in range(len(data)):
                        self.wfile.write(data[k : k + 1])
                        if owner._stopped.wait(owner.drip_s):
                            return
                except OSError:  # the client gave up: the point of the fault
                    return

            def _authorised(self) -> bool:
                if owner.required_key is None:
                    return True
                if self.headers.get("authorization") == f"Bearer {owner.required_key}":
                    return True
                self._send(
                    401, {"error": {"message": "invalid api key", "type": "invalid_request_error"}}
                )
                return False

            def do_GET(self) -> None:  # noqa: N802 - http.server's naming
                if not self._authorised():
                    return
                if owner.models_answer is not None:
                    content_type, text = owner.models_answer
                    self._send(200, text, content_type=content_type)
                    return
                self._send(200, {"object": "list", "data": [{"id": "fake-vlm", "object": "model"}]})

            def do_POST(self) -> None:  # noqa: N802
                body = json.loads(self.rfile.read(int(self.headers["content-length"])))
                if not self._authorised():
                    return
                with owner._lock:
                    owner.requests.append(body)
                    fault = owner.faults.popleft() if owner.faults else owner.persistent_fault
                if fault in ("429", "500"):
                    status = int(fault)
                    headers = {"retry-after": "0.05"} if status == 429 else None
                    self._send(status, {"error": {"message": f"fault {fault}"}}, headers)
                    return
                if fault == "401":  # the key revoked mid-run
                    self._send(401, {"error": {"message": "invalid api key"}})
                    return
                if fault == "html":
                    self._send(200, PROXY_PAGE)
                    return
                # A careless server quoting the credentials it was sent: the header as is,
                # or the key alone, as OpenAI's own "Incorrect API key provided" does.
                authorization = self.headers.get("authorization", "")
                key = authorization.removeprefix("Bearer ")
                if fault == "echo_key_500":
                    message = f"Incorrect API key provided: {key}. Upstream failed."
                    self._send(500, {"error": {"message": message}})
                    return
                if fault == "echo_key_html":
                    page = f"<!DOCTYPE html><pre>Authorization: {authorization}</pre>{PROXY_PAGE}"
                    self._send(200, page)
                    return
                if fault == "slow":
                    time.sleep(owner.slow_s)  # longer than the client's timeout
                if fault == "garbage":
                    text = "The cave is dark and I am not sure where to go."
                elif fault == "two_keys":
                    text = 'Two options:\n{"forward 0.5 m": "open", "turn left 10 deg": "wall"}'
                elif fault == "out_of_set":
                    text = 'I will go ahead a bit.\n{"forward 0.3 m": "gap ahead"}'
                elif fault == "drip":  # never read whole: its words do not matter
                    text = 'Slowly.\n{"forward 0.5 m": "open water"}'
                elif fault == "echo_key_reply":  # a model that repeats its prompt's secrets
                    with owner._lock:
                        text = f"My key is {key}; {authorization}.\n{owner.answer(body)}"
                else:
                    with owner._lock:
                        text = owner.answer(body)
                n_images = sum(
                    1
                    for m in body["messages"]
                    if isinstance(m["content"], list)
                    for p in m["content"]
                    if p["type"] == "image_url"
                )
                chars = sum(
                    len(json.dumps(m["content"]))
                    if isinstance(m["content"], str)
                    else sum(len(p.get("text", "")) for p in m["content"])
                    for m in body["messages"]
                )
                prompt_tokens = chars // 4 + 85 * n_images
                self._send(
                    200,
                    {
                        "id": f"chatcmpl-{len(owner.requests)}",
                        "object": "chat.completion",
                        "created": int(time.time()),
                        "model": body["model"],
                        "choices": [
                            {
                                "index": 0,
                                "finish_reason": "stop",
                                "message": {"role": "assistant", "content": text},
                            }
                        ],
                        "usage": {
                            "prompt_tokens": prompt_tokens,
                            "completion_tokens": len(text) // 4,
                            "total_tokens": prompt_tokens + len(text) // 4,
                        },
                    },
                    drip=fault == "drip",
                )

        return Handler
