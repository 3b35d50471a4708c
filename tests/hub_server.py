"""A small Hugging Face Hub-compatible HTTP server for tests, on 127.0.0.1 (stdlib only).

It implements only what ``huggingface_hub`` 1.x's real HTTP client calls when ``demo-factory publish``
uploads dataset repos and when ``LeRobotDataset(repo_id)`` downloads one (with ``HF_HUB_DISABLE_XET=1``,
so files go through the classic LFS protocol instead of Xet):

- ``GET  /api/whoami-v2``: identity of the token
- ``POST /api/validate-yaml``: README.md front matter check
- ``POST /api/repos/create``: a new repo (initial commit: ``.gitattributes``), 409 if it exists
- ``GET  /api/datasets/{repo}[/revision/{rev}]``: repo info (``sha``, ``siblings``, ``private``)
- ``PUT  /api/datasets/{repo}/settings``: visibility
- ``GET  /api/datasets/{repo}/tree/{rev}[/{path}]``: file listing (``recursive``; paginated with ``Link``)
- ``GET  /api/datasets/{repo}/refs``: branches and tags
- ``POST /api/datasets/{repo}/tag/{rev}``, ``DELETE /api/datasets/{repo}/tag/{tag}``: tags
- ``POST /api/datasets/{repo}/preupload/{rev}``: upload mode of each file (``lfs`` or ``regular``)
- ``POST /datasets/{repo}.git/info/lfs/objects/batch``: LFS batch API, ``basic`` transfer, with ``verify``
- ``PUT  <upload href>``, ``POST /datasets/{repo}.git/info/lfs/objects/verify``: an LFS object, PUT to a
  "storage" host name (``localhost``) without the token, as to a presigned S3 URL
- ``POST /api/datasets/{repo}/commit/{rev}``: NDJSON commit (``header``, ``file``, ``lfsFile``,
  ``deletedFile``, ``deletedFolder``)
- ``HEAD|GET /datasets/{repo}/resolve/{rev}/{path}``: a file; regular ones directly (``ETag`` = git blob id,
  ``X-Repo-Commit``, ``Content-Length``), LFS ones as the real Hub does: a 302 to a CDN URL on another host
  name (``localhost``) with ``X-Linked-Etag`` (the sha256) and ``X-Linked-Size``
- ``HEAD|GET <CDN href>``: the LFS object (``Range`` supported)

Only dataset repos are served. Repos, commits, branches and tags live in memory; file contents in a folder.
Errors carry ``X-Error-Code`` / ``X-Error-Message`` like the Hub's (``RepoNotFound``, ``RevisionNotFound``,
``EntryNotFound``), so the client raises its usual exceptions. Every request is recorded
(``HubServer.requests``: method, path, host, headers, status) and faults can be injected
(``HubServer.fail``: an HTTP status, or a connection dropped without a response).

A client process pointed at it with ``HF_ENDPOINT`` should call ``keep_on_loopback`` first: a few client
calls ignore ``HF_ENDPOINT`` (``RepoCard.validate`` posts to ``https://huggingface.co/api/validate-yaml``),
those are sent here instead, and any other connection beyond 127.0.0.1 fails.
"""

from __future__ import annotations

import base64
import fnmatch
import hashlib
import itertools
import json
import re
import secrets
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, quote, unquote, urlsplit

REPO_TYPE = "dataset"
PREFIX = "datasets"  # URL prefix of dataset repos
LFS_POINTER = "version https://git-lfs.github.com/spec/v1\noid sha256:{oid}\nsize {size}\n"
LFS_SIZE_THRESHOLD = 10 * 1024 * 1024  # the Hub stores larger files through LFS whatever their name
# A subset of the .gitattributes the Hub writes into a new dataset repo.
DEFAULT_GITATTRIBUTES = "".join(f"{pattern} filter=lfs diff=lfs merge=lfs -text\n" for pattern in (
    "*.7z", "*.arrow", "*.bin", "*.bz2", "*.ftz", "*.gz", "*.h5", "*.joblib", "*.lz4", "*.mds", "*.model",
    "*.msgpack", "*.npy", "*.npz", "*.onnx", "*.ot", "*.parquet", "*.pb", "*.pickle", "*.pkl", "*.pt", "*.pth",
    "*.rar", "*.safetensors", "*.tar", "*.tflite", "*.tgz", "*.wasm", "*.xz", "*.zip", "*.zst", "*tfevents*",
    "*.mp3", "*.ogg", "*.wav", "*.bmp", "*.gif", "*.png", "*.tiff", "*.jpg", "*.jpeg", "*.webp",
    "*.mp4", "*.webm"))


def git_blob_id(content: bytes) -> str:
    """The git object id of a blob (what the Hub calls a regular file's ``oid``)."""
    return hashlib.sha1(b"blob %d\0" % len(content) + content).hexdigest()


@dataclass(frozen=True)
class Blob:
    """A file in a commit: its content (by sha256) and whether the repo stores it through LFS."""

    sha256: str
    size: int
    lfs: bool
    blob_id: str  # git object id: of the content, or of the LFS pointer file

    @property
    def pointer(self) -> bytes:
        return LFS_POINTER.format(oid=self.sha256, size=self.size).encode()


@dataclass
class Commit:
    sha: str
    parent: str | None
    summary: str
    files: dict[str, Blob]
    date: str


@dataclass
class Repo:
    repo_id: str
    private: bool
    commits: dict[str, Commit] = field(default_factory=dict)
    branches: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)
    lfs: set[str] = field(default_factory=set)  # sha256 of the LFS objects uploaded to this repo
    created: str = ""

    def resolve(self, revision: str) -> str | None:
        """The commit sha of a branch, tag or commit sha; None when unknown."""
        if revision in self.branches:
            return self.branches[revision]
        if revision in self.tags:
            return self.tags[revision]
        return revision if revision in self.commits else None


@dataclass
class Fault:
    method: str
    pattern: re.Pattern
    status: int | None  # None: drop the connection without answering
    times: int
    hits: int = 0


@dataclass
class Recorded:
    method: str
    path: str  # with the query string
    host: str
    headers: dict[str, str]  # names lower-cased
    status: int | None = None  # None: dropped

    @property
    def authorization(self) -> str | None:
        return self.headers.get("authorization")


class HubError(Exception):
    def __init__(self, status: int, message: str, code: str | None = None, headers: dict | None = None):
        super().__init__(message)
        self.status, self.message, self.code, self.headers = status, message, code, headers or {}


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S.000Z", time.gmtime())


class HubServer:
    """The server: ``with HubServer(folder, token) as hub: ... hub.endpoint ...``."""

    def __init__(self, storage: Path, token: str, user: str = "me", orgs: tuple[str, ...] = ("my-lab",),
                 tree_page_size: int = 1000, cdn_host: str = "localhost"):
        self.storage = Path(storage)
        (self.storage / "objects").mkdir(parents=True, exist_ok=True)
        self.token, self.user, self.orgs = token, user, tuple(orgs)
        self.tree_page_size = tree_page_size
        self.cdn_host = cdn_host  # the "storage/CDN" host of LFS objects; another name for 127.0.0.1
        self.repos: dict[str, Repo] = {}
        self.requests: list[Recorded] = []
        self.faults: list[Fault] = []
        self.signature = secrets.token_hex(8)  # stands for the presigned part of storage URLs
        self.lock = threading.RLock()
        self._counter = itertools.count()
        self._httpd: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    # -- life cycle ----------------------------------------------------------------------------
    def start(self) -> HubServer:
        handler = type("Handler", (_Handler,), {"hub": self})
        self._httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="hub-server", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._thread.join(timeout=10)
            self._httpd = None

    def __enter__(self) -> HubServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def port(self) -> int:
        return self._httpd.server_address[1]

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def cdn(self) -> str:
        return f"http://{self.cdn_host}:{self.port}"

    # -- for tests -----------------------------------------------------------------------------
    def fail(self, method: str, path_pattern: str, status: int | None = 500, times: int = 1) -> Fault:
        """The next ``times`` requests ``method`` whose path matches ``path_pattern`` (re.search) fail:
        with ``status``, or by closing the connection without an answer when ``status`` is None."""
        fault = Fault(method.upper(), re.compile(path_pattern), status, times)
        with self.lock:
            self.faults.append(fault)
        return fault

    def files(self, repo_id: str, revision: str = "main") -> dict[str, bytes]:
        """Path -> content of a repo at a revision."""
        with self.lock:
            repo = self.repos[repo_id]
            commit = repo.commits[repo.resolve(revision)]
            return {path: self.read_object(blob.sha256) for path, blob in commit.files.items()}

    def head(self, repo_id: str, branch: str = "main") -> str:
        with self.lock:
            return self.repos[repo_id].branches[branch]

    def requests_since(self, mark: int) -> list[Recorded]:
        with self.lock:
            return self.requests[mark:]

    # -- storage -------------------------------------------------------------------------------
    def store_object(self, content: bytes) -> str:
        sha = hashlib.sha256(content).hexdigest()
        path = self.storage / "objects" / sha
        if not path.exists():
            tmp = path.with_suffix(f".tmp{next(self._counter)}")
            tmp.write_bytes(content)
            tmp.replace(path)
        return sha

    def read_object(self, sha256: str) -> bytes:
        return (self.storage / "objects" / sha256).read_bytes()

    def new_commit(self, repo: Repo, parent: str | None, summary: str, files: dict[str, Blob]) -> Commit:
        listing = json.dumps([parent, summary, sorted((p, b.blob_id) for p, b in files.items()),
                              next(self._counter)]).encode()
        commit = Commit(hashlib.sha1(listing).hexdigest(), parent, summary, dict(files), _now())
        repo.commits[commit.sha] = commit
        return commit

    def blob(self, content: bytes, lfs: bool) -> Blob:
        sha = self.store_object(content)
        pointer = LFS_POINTER.format(oid=sha, size=len(content)).encode()
        return Blob(sha, len(content), lfs, git_blob_id(pointer if lfs else content))


# ---------------------------------------------------------------------------------------------------
def _lfs_patterns(gitattributes: bytes) -> list[str]:
    patterns = []
    for line in gitattributes.decode("utf-8", "replace").splitlines():
        parts = line.split()
        if len(parts) > 1 and not parts[0].startswith("#") and "filter=lfs" in parts[1:]:
            patterns.append(parts[0])
    return patterns


def _matches(path: str, pattern: str) -> bool:
    """gitattributes matching, simplified: patterns without '/' match the file name."""
    if "/" in pattern:
        return fnmatch.fnmatchcase(path, pattern.lstrip("/"))
    return fnmatch.fnmatchcase(path.rsplit("/", 1)[-1], pattern)


class _Handler(BaseHTTPRequestHandler):
    hub: HubServer  # set on the subclass made by HubServer.start
    protocol_version = "HTTP/1.1"
    server_version = "demo-factory-test-hub/0.1"

    def log_message(self, format, *args):  # keep the test output clean
        pass

    # -- plumbing -------------------------------------------------------------------------------
    def do_GET(self):
        self._handle()

    def do_HEAD(self):
        self._handle()

    def do_POST(self):
        self._handle()

    def do_PUT(self):
        self._handle()

    def do_DELETE(self):
        self._handle()

    def _read_body(self) -> bytes:
        if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
            chunks = []
            while True:
                size = int(self.rfile.readline().split(b";")[0].strip() or b"0", 16)
                if size == 0:
                    while self.rfile.readline() not in (b"\r\n", b"\n", b""):
                        pass  # trailers
                    return b"".join(chunks)
                chunks.append(self.rfile.read(size))
                self.rfile.readline()
        length = int(self.headers.get("Content-Length") or 0)
        return self.rfile.read(length) if length else b""

    def _handle(self) -> None:
        hub = self.hub
        split = urlsplit(self.path)
        self.route_path, self.query = split.path, parse_qs(split.query)
        self.body = self._read_body()
        record = Recorded(self.command, self.path, self.headers.get("Host", ""),
                          {k.lower(): v for k, v in self.headers.items()})
        self.record = record
        with hub.lock:
            hub.requests.append(record)
            fault = next((f for f in hub.faults if f.hits < f.times and f.method == self.command
                          and f.pattern.search(self.route_path)), None)
            if fault is not None:
                fault.hits += 1
        if fault is not None:
            if fault.status is None:
                self.close_connection = True  # no answer at all: the client sees the connection drop
                return
            return self._send_json({"error": "injected failure"}, fault.status)
        try:
            self._dispatch()
        except HubError as error:
            headers = {"X-Error-Message": error.message, **error.headers}
            if error.code:
                headers["X-Error-Code"] = error.code
            self._send_json({"error": error.message}, error.status, headers)

    def _send(self, status: int, body: bytes = b"", headers: dict | None = None,
              content_type: str = "application/json") -> None:
        self.record.status = status
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        for name, value in (headers or {}).items():
            self.send_header(name, str(value))
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD" and body:
            self.wfile.write(body)

    def _send_json(self, data, status: int = 200, headers: dict | None = None, content_type="application/json"):
        self._send(status, json.dumps(data).encode(), headers, content_type)

    def _json(self) -> dict:
        try:
            return json.loads(self.body or b"{}")
        except ValueError:
            raise HubError(400, "the body is not JSON") from None

    # -- auth -------------------------------------------------------------------------------------
    def _caller(self) -> str | None:
        """The user of a valid token, None without one; 401 for a wrong one (as the Hub)."""
        header = self.headers.get("Authorization")
        if header is None:
            return None
        if header != f"Bearer {self.hub.token}":
            raise HubError(401, "Invalid credentials in Authorization header")
        return self.hub.user

    def _repo(self, repo_id: str, write: bool = False) -> Repo:
        caller = self._caller()
        repo = self.hub.repos.get(repo_id)
        if repo is None or (repo.private and caller is None):
            raise HubError(404, "Repository not found", "RepoNotFound")
        if write:
            if caller is None:
                raise HubError(401, "You must be authenticated to write")
            if repo_id.split("/")[0] not in (self.hub.user, *self.hub.orgs):
                raise HubError(403, f"You don't have the rights to write to {repo_id}")
        return repo

    def _commit(self, repo: Repo, revision: str) -> Commit:
        sha = repo.resolve(unquote(revision))
        if sha is None:
            raise HubError(404, f"Invalid rev id: {unquote(revision)}", "RevisionNotFound")
        return repo.commits[sha]

    # -- routing ---------------------------------------------------------------------------------
    def _dispatch(self) -> None:
        path, method = self.route_path, self.command
        with self.hub.lock:
            if path == "/api/whoami-v2" and method == "GET":
                return self._whoami()
            if path == "/api/validate-yaml" and method == "POST":
                return self._validate_yaml()
            if path == "/api/repos/create" and method == "POST":
                return self._create_repo()
            if m := re.fullmatch(rf"/api/{PREFIX}/([^/]+/[^/]+)(/.*)?", path):
                return self._repo_api(unquote(m.group(1)), m.group(2) or "", method)
            if m := re.fullmatch(rf"/{PREFIX}/([^/]+/[^/]+)\.git/info/lfs/objects/(batch|verify)", path):
                if method == "POST":
                    return self._lfs_batch(unquote(m.group(1))) if m.group(2) == "batch" \
                        else self._lfs_verify(unquote(m.group(1)))
            if m := re.fullmatch(rf"/{PREFIX}/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", path):
                if method in ("GET", "HEAD"):
                    return self._resolve(unquote(m.group(1)), m.group(2), unquote(m.group(3)))
            if m := re.fullmatch(r"/lfs-storage/([^/]+/[^/]+)/([0-9a-f]{64})", path):
                if method == "PUT":
                    return self._lfs_put(unquote(m.group(1)), m.group(2))
                if method in ("GET", "HEAD"):
                    return self._cdn(unquote(m.group(1)), m.group(2))
        raise HubError(404, f"Not implemented by the test Hub: {method} {path}")

    def _repo_api(self, repo_id: str, rest: str, method: str) -> None:
        if method == "GET" and rest in ("", "/"):
            return self._info(repo_id, "main")
        if method == "GET" and (m := re.fullmatch(r"/revision/([^/]+)", rest)):
            return self._info(repo_id, m.group(1))
        if method == "GET" and (m := re.fullmatch(r"/tree/([^/]+)(/.*)?", rest)):
            return self._tree(repo_id, m.group(1), unquote((m.group(2) or "").strip("/")))
        if method == "GET" and rest == "/refs":
            return self._refs(repo_id)
        if method == "POST" and (m := re.fullmatch(r"/preupload/([^/]+)", rest)):
            return self._preupload(repo_id, m.group(1))
        if method == "POST" and (m := re.fullmatch(r"/commit/([^/]+)", rest)):
            return self._commit_api(repo_id, m.group(1))
        if method == "POST" and (m := re.fullmatch(r"/tag/([^/]+)", rest)):
            return self._create_tag(repo_id, m.group(1))
        if method == "DELETE" and (m := re.fullmatch(r"/tag/([^/]+)", rest)):
            return self._delete_tag(repo_id, unquote(m.group(1)))
        if method == "PUT" and rest == "/settings":
            return self._settings(repo_id)
        raise HubError(404, f"Not implemented by the test Hub: {method} /api/{PREFIX}/{repo_id}{rest}")

    # -- account ---------------------------------------------------------------------------------
    def _whoami(self) -> None:
        if self._caller() is None:
            raise HubError(401, "Invalid username or password.")
        self._send_json({"type": "user", "id": "0" * 24, "name": self.hub.user, "fullname": self.hub.user,
                         "orgs": [{"type": "org", "name": org} for org in self.hub.orgs],
                         "auth": {"type": "access_token", "accessToken": {"displayName": "test", "role": "write"}}})

    def _validate_yaml(self) -> None:
        import yaml  # huggingface_hub depends on PyYAML

        content = self._json().get("content", "")
        match = re.match(r"^---\s*\n(.*?)\n---\s*(\n|$)", content, re.DOTALL)
        try:
            data = yaml.safe_load(match.group(1)) if match else {}
        except yaml.YAMLError as error:
            return self._send_json({"errors": [{"message": f"Invalid YAML: {error}"}]}, 400)
        if data is not None and not isinstance(data, dict):
            return self._send_json({"errors": [{"message": "The metadata must be a YAML mapping"}]}, 400)
        self._send_json({"errors": [], "warnings": []})

    # -- repos -----------------------------------------------------------------------------------
    def _create_repo(self) -> None:
        if self._caller() is None:
            raise HubError(401, "You must be authenticated to create a repo")
        body = self._json()
        if body.get("type", "model") != REPO_TYPE:
            raise HubError(400, "The test Hub serves dataset repos only")
        name, owner = body.get("name"), body.get("organization") or self.hub.user
        if not name or owner not in (self.hub.user, *self.hub.orgs):
            raise HubError(403, f"You don't have the rights to create a repo under {owner!r}")
        repo_id = f"{owner}/{name}"
        url = f"{self.hub.endpoint}/{PREFIX}/{repo_id}"
        if repo_id in self.hub.repos:
            return self._send_json({"error": f"You already created this {REPO_TYPE} repo", "url": url}, 409)
        private = body.get("visibility") == "private" if "visibility" in body else bool(body.get("private"))
        repo = Repo(repo_id, private, created=_now())
        attributes = self.hub.blob(DEFAULT_GITATTRIBUTES.encode(), lfs=False)
        repo.branches["main"] = self.hub.new_commit(repo, None, "initial commit", {".gitattributes": attributes}).sha
        self.hub.repos[repo_id] = repo
        self._send_json({"url": url, "name": repo_id, "id": "0" * 24})

    def _info(self, repo_id: str, revision: str) -> None:
        repo = self._repo(repo_id)
        commit = self._commit(repo, revision)
        self._send_json({
            "_id": "0" * 24, "id": repo_id, "author": repo_id.split("/")[0], "sha": commit.sha,
            "private": repo.private, "gated": False, "disabled": False, "downloads": 0, "likes": 0,
            "tags": [], "createdAt": repo.created, "lastModified": commit.date,
            "siblings": [{"rfilename": p} for p in sorted(commit.files)],
            "usedStorage": sum(b.size for b in commit.files.values()),
        })

    def _settings(self, repo_id: str) -> None:
        repo = self._repo(repo_id, write=True)
        body = self._json()
        if "visibility" in body:
            repo.private = body["visibility"] == "private"
        elif "private" in body:
            repo.private = bool(body["private"])
        self._send_json({})

    def _tree(self, repo_id: str, revision: str, folder: str) -> None:
        repo = self._repo(repo_id)
        commit = self._commit(repo, revision)
        recursive = self.query.get("recursive", ["false"])[0].lower() in ("true", "1")
        prefix = f"{folder}/" if folder else ""
        if folder and folder in commit.files:
            raise HubError(400, f"{folder} is a file, not a folder")
        below = {p: b for p, b in commit.files.items() if p.startswith(prefix)}
        if folder and not below:
            raise HubError(404, f"{folder} does not exist in {revision}", "EntryNotFound")
        folders = {prefix + "/".join(p[len(prefix):].split("/")[:i])
                   for p in below for i in range(1, p[len(prefix):].count("/") + 1)}
        entries = []
        for path in sorted(folders | set(below)):
            if not recursive and "/" in path[len(prefix):]:
                continue
            if path in folders:
                oid = hashlib.sha1(("tree " + path + repr(sorted((p, b.blob_id) for p, b in below.items()
                                                               if p.startswith(path + "/")))).encode()).hexdigest()
                entries.append({"type": "directory", "oid": oid, "size": 0, "path": path})
            else:
                blob = below[path]
                entry = {"type": "file", "oid": blob.blob_id, "size": blob.size, "path": path}
                if blob.lfs:
                    entry["lfs"] = {"oid": blob.sha256, "size": blob.size, "pointerSize": len(blob.pointer)}
                entries.append(entry)
        start = int(self.query.get("cursor", ["0"])[0])
        page = entries[start:start + self.hub.tree_page_size]
        headers = {}
        if start + self.hub.tree_page_size < len(entries):
            query = f"recursive={str(recursive).lower()}&expand=false&cursor={start + self.hub.tree_page_size}"
            next_url = f"{self.hub.endpoint}{self.route_path}?{query}"
            headers["Link"] = f'<{next_url}>; rel="next"'
        self._send_json(page, headers=headers)

    def _refs(self, repo_id: str) -> None:
        repo = self._repo(repo_id)

        def refs(kind, items):
            return [{"name": n, "ref": f"refs/{kind}/{n}", "targetCommit": sha} for n, sha in sorted(items.items())]

        data = {"branches": refs("heads", repo.branches), "tags": refs("tags", repo.tags), "converts": []}
        if "include_prs" in self.query:
            data["pullRequests"] = []
        self._send_json(data)

    def _create_tag(self, repo_id: str, revision: str) -> None:
        repo = self._repo(repo_id, write=True)
        commit = self._commit(repo, revision)
        tag = self._json().get("tag")
        if not tag:
            raise HubError(400, "tag is required")
        if tag in repo.tags or tag in repo.branches:
            raise HubError(409, f"Reference refs/tags/{tag} already exists")
        repo.tags[tag] = commit.sha
        self._send_json({})

    def _delete_tag(self, repo_id: str, tag: str) -> None:
        repo = self._repo(repo_id, write=True)
        if repo.tags.pop(tag, None) is None:
            raise HubError(404, f"Invalid rev id: {tag}", "RevisionNotFound")
        self._send_json({})

    # -- uploads ---------------------------------------------------------------------------------
    def _preupload(self, repo_id: str, revision: str) -> None:
        repo = self._repo(repo_id, write=True)
        commit = self._commit(repo, revision)
        attributes = commit.files.get(".gitattributes")
        patterns = _lfs_patterns(self.hub.read_object(attributes.sha256)) if attributes else []
        answers = []
        for item in self._json().get("files", []):
            path, size = item["path"], int(item["size"])
            sample = base64.b64decode(item.get("sample", ""))
            lfs = size > LFS_SIZE_THRESHOLD or b"\0" in sample or any(_matches(path, p) for p in patterns)
            existing = commit.files.get(path)
            oid = None if existing is None else (existing.sha256 if existing.lfs else existing.blob_id)
            answers.append({"path": path, "uploadMode": "lfs" if lfs else "regular", "shouldIgnore": False,
                            "oid": oid})
        self._send_json({"files": answers, "commitOid": commit.sha})

    def _lfs_batch(self, repo_id: str) -> None:
        repo = self._repo(repo_id, write=True)
        body = self._json()
        if body.get("operation") != "upload":
            raise HubError(400, "The test Hub's LFS batch API serves uploads only")
        objects = []
        for item in body.get("objects", []):
            oid, size = item["oid"], int(item["size"])
            entry = {"oid": oid, "size": size, "authenticated": True}
            if oid not in repo.lfs:  # already stored objects get no actions: the client skips them
                entry["actions"] = {
                    "upload": {"href": f"{self.hub.cdn}/lfs-storage/{quote(repo_id)}/{oid}"
                                       f"?X-Amz-Signature={self.hub.signature}"},
                    "verify": {"href": f"{self.hub.endpoint}/{PREFIX}/{repo_id}.git/info/lfs/objects/verify",
                               "header": {}},
                }
            objects.append(entry)
        self._send_json({"transfer": "basic", "objects": objects, "hash_algo": "sha256"},
                        content_type="application/vnd.git-lfs+json")

    def _lfs_put(self, repo_id: str, oid: str) -> None:
        if self.query.get("X-Amz-Signature") != [self.hub.signature]:
            raise HubError(403, "SignatureDoesNotMatch")
        repo = self.hub.repos.get(repo_id)
        if repo is None:
            raise HubError(404, "NoSuchBucket")
        if hashlib.sha256(self.body).hexdigest() != oid:
            raise HubError(400, "BadDigest: the content does not match the object id")
        self.hub.store_object(self.body)
        repo.lfs.add(oid)
        self._send(200, headers={"ETag": f'"{hashlib.md5(self.body).hexdigest()}"'})

    def _lfs_verify(self, repo_id: str) -> None:
        repo = self._repo(repo_id, write=True)
        body = self._json()
        oid, size = body.get("oid"), body.get("size")
        if oid not in repo.lfs or (self.hub.storage / "objects" / oid).stat().st_size != size:
            raise HubError(404, f"LFS object {oid} not found")
        self._send_json({"success": True})

    def _commit_api(self, repo_id: str, revision: str) -> None:
        repo = self._repo(repo_id, write=True)
        branch = unquote(revision)
        if branch not in repo.branches:
            raise HubError(404, f"Invalid rev id: {branch}", "RevisionNotFound")
        head = repo.commits[repo.branches[branch]]
        files = dict(head.files)
        header = None
        for line in self.body.splitlines():
            if not line.strip():
                continue
            item = json.loads(line)
            key, value = item.get("key"), item.get("value", {})
            if key == "header":
                header = value
                parent = value.get("parentCommit")
                if parent is not None and parent != head.sha:
                    raise HubError(412, "A commit has happened since. Please refresh and try again.")
            elif key == "file":
                if value.get("encoding") != "base64":
                    raise HubError(400, "file content must be base64")
                files[value["path"]] = self.hub.blob(base64.b64decode(value["content"]), lfs=False)
            elif key == "lfsFile":
                oid, size = value["oid"], int(value["size"])
                if value.get("algo", "sha256") != "sha256" or oid not in repo.lfs:
                    raise HubError(422, f"LFS file {value['path']} ({oid}) was not uploaded")
                files[value["path"]] = Blob(oid, size, True,
                                            git_blob_id(LFS_POINTER.format(oid=oid, size=size).encode()))
            elif key == "deletedFile":
                if files.pop(value["path"], None) is None:
                    raise HubError(404, f"A file with this name doesn't exist: {value['path']}", "EntryNotFound")
            elif key == "deletedFolder":
                folder = value["path"].rstrip("/") + "/"
                for path in [p for p in files if p.startswith(folder)]:
                    del files[path]
            else:
                raise HubError(400, f"Unknown commit operation {key!r}")
        if header is None:
            raise HubError(400, "The commit has no header")
        commit = self.hub.new_commit(repo, head.sha, header.get("summary", ""), files)
        repo.branches[branch] = commit.sha
        self._send_json({"success": True, "commitOid": commit.sha, "pullRequestUrl": None,
                         "commitUrl": f"{self.hub.endpoint}/{PREFIX}/{repo_id}/commit/{commit.sha}"})

    # -- downloads -------------------------------------------------------------------------------
    def _resolve(self, repo_id: str, revision: str, path: str) -> None:
        repo = self._repo(repo_id)
        commit = self._commit(repo, revision)
        blob = commit.files.get(path)
        if blob is None:
            raise HubError(404, f"Entry not found: {path}", "EntryNotFound", {"X-Repo-Commit": commit.sha})
        headers = {"X-Repo-Commit": commit.sha, "ETag": f'"{blob.blob_id}"', "Accept-Ranges": "bytes"}
        if blob.lfs:  # like the Hub: a redirect to a signed URL on the CDN, the metadata on the redirect
            location = f"{self.hub.cdn}/lfs-storage/{quote(repo_id)}/{blob.sha256}?X-Amz-Signature={self.hub.signature}"
            headers.update({"Location": location, "X-Linked-Etag": f'"{blob.sha256}"', "X-Linked-Size": blob.size})
            return self._send(302, headers=headers, content_type="text/plain")
        self._send_content(self.hub.read_object(blob.sha256), headers)

    def _cdn(self, repo_id: str, oid: str) -> None:
        if self.query.get("X-Amz-Signature") != [self.hub.signature]:
            raise HubError(403, "SignatureDoesNotMatch")
        repo = self.hub.repos.get(repo_id)
        if repo is None or oid not in repo.lfs:
            raise HubError(404, "NoSuchKey")
        self._send_content(self.hub.read_object(oid), {"ETag": f'"{oid}"', "Accept-Ranges": "bytes"})

    def _send_content(self, content: bytes, headers: dict) -> None:
        ranged = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", "").strip())
        if ranged:
            start = int(ranged.group(1))
            end = min(int(ranged.group(2)) if ranged.group(2) else len(content) - 1, len(content) - 1)
            if start >= len(content):
                return self._send(416, headers={"Content-Range": f"bytes */{len(content)}"})
            headers = {**headers, "Content-Range": f"bytes {start}-{end}/{len(content)}"}
            return self._send(206, content[start:end + 1], headers, "application/octet-stream")
        self._send(200, content, headers, "application/octet-stream")


# ---------------------------------------------------------------------------------------------------
PUBLIC_HUB_HOSTS = ("huggingface.co", "hub-ci.huggingface.co")


def keep_on_loopback(endpoint: str) -> None:
    """For a process whose ``huggingface_hub`` client talks to the test Hub at ``endpoint`` (HF_ENDPOINT).

    The client's few requests that ignore HF_ENDPOINT and go to ``https://huggingface.co`` (``RepoCard.validate``)
    are sent to ``endpoint`` instead (they arrive with ``Host: huggingface.co``), and any connection beyond
    the loopback interface fails, so a test that uses it needs no network. Call it before anything uses the
    client.
    """
    import ipaddress
    import socket

    import httpx
    from huggingface_hub import get_session, set_client_factory

    target = httpx.URL(endpoint)
    hooks = get_session().event_hooks  # the default client's (offline check, request ids), kept on ours

    class Route(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if request.url.host in PUBLIC_HUB_HOSTS:
                request.url = request.url.copy_with(scheme=target.scheme, host=target.host, port=target.port)
            return super().handle_request(request)

    def client() -> httpx.Client:  # huggingface_hub's default client, with the transport above
        return httpx.Client(transport=Route(), event_hooks=hooks, follow_redirects=True, timeout=None)

    set_client_factory(client)

    def loopback_only(connect):
        def guarded(self, address):
            if self.family in (socket.AF_INET, socket.AF_INET6):
                host = address[0]
                try:
                    allowed = ipaddress.ip_address(host.split("%")[0]).is_loopback
                except ValueError:
                    allowed = host == "localhost"
                if not allowed:
                    raise ConnectionRefusedError(f"the test allows no network: connection to {host} refused")
            return connect(self, address)
        return guarded

    socket.socket.connect = loopback_only(socket.socket.connect)
    socket.socket.connect_ex = loopback_only(socket.socket.connect_ex)
