"""The collection web server: the page, its JSON API and the variation pictures.

Standard library only (``http.server.ThreadingHTTPServer``). Routes:

    GET  /                                   the page (static files from ``static/``, no build step)
    GET  /static/<file>                      app.js, style.css
    GET  /api/state?writer=W                 task, limits, progress, W's last entry
    GET  /api/next?writer=W&after=ID&skipped=ID,ID   the variation W should describe next
    GET  /api/variation/<id>                 one test variation (its pictures)
    POST /api/instructions                   {"writer", "variation_id", "instruction"} → 201
    PUT  /api/instructions/last              {"writer", "instruction"}: edit W's last entry
    GET  /pictures/<version>/<id>/<name>.png the variation's pictures (rendered lazily, cached)

Errors are JSON ``{"error": message}`` with a 4xx status. Nothing the server returns is HTML built
from input: the page sets all text with ``textContent``, and a strict Content-Security-Policy
(scripts and styles only from this server, no inline code) backs that up. Writes must be
``application/json``, which a foreign web page cannot send here without a CORS preflight (never
granted), and when bound to a loopback address only loopback ``Host`` names are answered, so other
sites cannot reach the API through the writer's browser.
"""

from __future__ import annotations

import ipaddress
import json
import socket
import sys
import traceback
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

from demo_factory.collect.pictures import RENDER_VERSION, PictureCache, pictures_for
from demo_factory.collect.store import (
    INSTRUCTION_MAX_CHARS,
    INSTRUCTION_MIN_CHARS,
    WRITER_MAX_CHARS,
    EntryError,
    InstructionFile,
    check_writer,
    entry_json,
)
from demo_factory.instructions.human import HumanInstructionError

MAX_BODY_BYTES = 16 * 1024
STATIC_FILES = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
}
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
                               "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}
LOOPBACK_HOSTS = {"localhost", "127.0.0.1", "::1"}


@dataclass
class Response:
    status: int
    body: bytes
    content_type: str = "application/json; charset=utf-8"
    headers: dict[str, str] = field(default_factory=lambda: {"Cache-Control": "no-store"})


def json_response(payload, status: int = 200) -> Response:
    # <, > and & as \u escapes: the JSON means the same, and no byte of it can ever read as markup.
    text = json.dumps(payload).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
    return Response(status, text.encode("utf-8"))


def error_response(message: str, status: int) -> Response:
    return json_response({"error": message}, status)


def static_file(name: str) -> bytes:
    return (resources.files("demo_factory.collect") / "static" / name).read_bytes()


class CollectApp:
    """What the server answers, independent of the HTTP plumbing."""

    def __init__(self, instructions: InstructionFile, pictures: PictureCache):
        self.instructions = instructions
        self.pictures = pictures
        self.task = instructions.task
        self.static = {name: static_file(name) for name in STATIC_FILES}

    # -- payloads ----------------------------------------------------------------------------
    def variation_json(self, variation_id: int) -> dict:
        return {
            "id": variation_id,
            "index": self.instructions.order.index(variation_id) + 1,
            "count": self.instructions.counts()[variation_id],
            "pictures": [{"url": f"/pictures/{RENDER_VERSION}/{variation_id}/{p.name}.png", "caption": p.caption}
                         for p in pictures_for(self.task)],
        }

    def state_json(self, writer: str | None) -> dict:
        last = self.instructions.last_entry(writer) if writer else None
        return {
            "task": self.task.name,
            "language": self.instructions.language,
            "limits": {"instruction_min": INSTRUCTION_MIN_CHARS, "instruction_max": INSTRUCTION_MAX_CHARS,
                       "writer_max": WRITER_MAX_CHARS},
            "progress": self.instructions.progress(writer),
            "last": {**entry_json(last), "variation": self.variation_json(last.variation_id)} if last else None,
        }

    # -- routing -----------------------------------------------------------------------------
    def respond(self, method: str, target: str, content_type: str | None, body: bytes | None) -> Response:
        url = urlsplit(target)
        path = url.path
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        try:
            if method == "GET":
                return self._get(path, query)
            if method in ("POST", "PUT"):
                payload = self._json_body(content_type, body)
                if method == "POST" and path == "/api/instructions":
                    entry = self.instructions.add(payload.get("writer"), payload.get("variation_id"),
                                                  payload.get("instruction"))
                    return json_response({"entry": entry_json(entry), "state": self.state_json(entry.author)}, 201)
                if method == "PUT" and path == "/api/instructions/last":
                    entry = self.instructions.edit_last(payload.get("writer"), payload.get("instruction"))
                    return json_response({"entry": entry_json(entry), "state": self.state_json(entry.author)})
            return error_response(f"no such resource: {method} {path}", 404 if method in ("GET", "POST", "PUT") else 405)
        except EntryError as exc:
            return error_response(str(exc), exc.status)
        except HumanInstructionError as exc:  # someone broke the file while the server runs
            return error_response(f"the instruction file cannot be read: {exc}", 500)

    def _get(self, path: str, query: dict[str, str]) -> Response:
        if path in ("/", "/index.html"):
            return self._static("index.html")
        if path.startswith("/static/") and path[len("/static/"):] in STATIC_FILES:
            return self._static(path[len("/static/"):])
        if path == "/api/state":
            writer = check_writer(query["writer"]) if query.get("writer") else None
            return json_response(self.state_json(writer))
        if path == "/api/next":
            writer = check_writer(query.get("writer"))
            after = self._variation_id(query["after"]) if query.get("after") else None
            skipped = {self._variation_id(v) for v in query.get("skipped", "").split(",") if v}
            chosen = self.instructions.next_for(writer, after, skipped)
            return json_response({"variation": self.variation_json(chosen) if chosen is not None else None})
        parts = path.strip("/").split("/")
        if len(parts) == 3 and parts[:2] == ["api", "variation"]:
            return json_response({"variation": self.variation_json(self._variation_id(parts[2]))})
        if len(parts) == 4 and parts[:2] == ["pictures", RENDER_VERSION] and parts[3].endswith(".png"):
            variation_id, name = self._variation_id(parts[2]), parts[3][:-len(".png")]
            if name in self.pictures.names:
                png = self.pictures.png(variation_id, name)
                # The URL names the render version: its bytes never change.
                return Response(200, png, "image/png", {"Cache-Control": "public, max-age=31536000, immutable"})
        return error_response(f"no such resource: GET {path}", 404)

    def _static(self, name: str) -> Response:
        return Response(200, self.static[name], STATIC_FILES[name])

    def _variation_id(self, text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value not in self.instructions.order:
            raise EntryError(f"{text!r} is not a test variation of {self.task.name}", 404)
        return value

    @staticmethod
    def _json_body(content_type: str | None, body: bytes | None) -> dict:
        if (content_type or "").split(";")[0].strip().lower() != "application/json":
            raise EntryError("send the body as application/json", 415)
        try:
            payload = json.loads((body or b"").decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise EntryError("the body is not valid JSON") from None
        if not isinstance(payload, dict):
            raise EntryError("the body must be a JSON object")
        return payload


class _Handler(BaseHTTPRequestHandler):
    server_version = "demo-factory-collect"
    protocol_version = "HTTP/1.1"  # keep-alive: the page loads several pictures at once

    def do_GET(self):
        self._serve()

    def do_POST(self):
        self._serve()

    def do_PUT(self):
        self._serve()

    def _serve(self):
        response = self._checked_request()
        if response is not None:
            self.close_connection = True  # a body, if any, stays unread
        else:
            try:
                response = self.server.app.respond(self.command, self.path, self.headers.get("Content-Type"),
                                                   self._body())
            except Exception:  # a bug: answer and log it, keep serving the other writers
                traceback.print_exc(file=sys.stderr)
                response = error_response("internal error; see the server's output", 500)
        self.send_response(response.status)
        for name, value in {**SECURITY_HEADERS, **response.headers}.items():
            self.send_header(name, value)
        self.send_header("Content-Type", response.content_type)
        self.send_header("Content-Length", str(len(response.body)))
        self.end_headers()
        self.wfile.write(response.body)

    def _checked_request(self) -> Response | None:
        if self.server.loopback_only:
            host = host_name(self.headers.get("Host") or "")
            if host not in LOOPBACK_HOSTS:
                return error_response(f"unexpected Host {host!r}; open the page at http://localhost", 403)
        length = self.headers.get("Content-Length")
        if self.command in ("POST", "PUT"):
            if length is None or not length.isdigit():
                return error_response("a Content-Length is required", 411)
            if int(length) > MAX_BODY_BYTES:
                return error_response(f"the body is larger than {MAX_BODY_BYTES} bytes", 413)
        return None

    def _body(self) -> bytes | None:
        length = int(self.headers.get("Content-Length") or 0)
        return self.rfile.read(length) if length else None

    def log_message(self, format, *args):  # noqa: A002 - the stdlib's signature
        pass  # one line per picture would drown the useful output


class CollectServer(ThreadingHTTPServer):
    """A threaded HTTP server for one ``CollectApp``; ``port=0`` picks a free port."""

    daemon_threads = True
    request_queue_size = 128  # the default 5 resets connections when many browsers load pictures at once

    def __init__(self, app: CollectApp, host: str = "127.0.0.1", port: int = 8000):
        self.app = app
        self.address_family = _address_family(host)
        try:
            self.loopback_only = ipaddress.ip_address(socket.getaddrinfo(host, None)[0][4][0]).is_loopback
        except (socket.gaierror, ValueError):
            self.loopback_only = False
        super().__init__((host, port), _Handler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def host_name(host_header: str) -> str:
    """The name in a Host header, without port or IPv6 brackets, lower-case."""
    header = host_header.strip().lower()
    if header.startswith("["):
        return header[1:].split("]", 1)[0]
    return header.split(":", 1)[0]


def _address_family(host: str) -> socket.AddressFamily:
    try:
        return socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0][0]
    except socket.gaierror:
        return socket.AF_INET
