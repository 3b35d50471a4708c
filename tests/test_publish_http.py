"""`demo-factory publish` through huggingface_hub's real HTTP client, against the test Hub of ``hub_server.py``.

The publish command runs as a user runs it, in its own process with ``HF_ENDPOINT`` pointing at a small
Hub-compatible server on 127.0.0.1 (``HF_HUB_DISABLE_XET=1``: files go through the classic LFS protocol,
which the server implements; Xet it does not). The server drops the connection on one commit, so the first
run stops half-way; the same command run again finishes, sending only what is missing. Then a fresh process
with an empty cache loads every split with ``LeRobotDataset(repo_id)`` from the server and compares it with
the local split. The token must be sent to the Hub API, never to the file storage, and never printed.
No network: each process refuses connections beyond 127.0.0.1 (``hub_server.keep_on_loopback``).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hub_server import HubServer

TOKEN = "hf_TestTokenThatMustNeverAppear0123456789"
USER = "me"
REPO_ID = "me/pb"
TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent

# A child process whose huggingface_hub client stays on 127.0.0.1, then `demo-factory <argv>`.
CLI = f"""
import os, sys
sys.path.insert(0, {str(TESTS)!r})
import hub_server
hub_server.keep_on_loopback(os.environ["HF_ENDPOINT"])
from demo_factory.cli import main
sys.exit(main(sys.argv[1:]))
"""

# A child process loading each split from the Hub (empty cache) and locally; prints a JSON comparison.
LOADER = f"""
import json, os, sys
sys.path.insert(0, {str(TESTS)!r})
import hub_server
hub_server.keep_on_loopback(os.environ["HF_ENDPOINT"])
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

def same(a, b):
    if isinstance(b, torch.Tensor):
        return isinstance(a, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    return a == b

report = {{}}
for repo_id, root in json.loads(sys.argv[1]).items():
    remote = LeRobotDataset(repo_id)  # from HF_ENDPOINT into HF_LEROBOT_HOME/hub
    local = LeRobotDataset(repo_id, root=root)
    indices = sorted({{0, len(local) // 2, len(local) - 1}})
    differences = [f"{{i}}:{{key}}" for i in indices for a, b in [(remote[i], local[i])]
                   for key in sorted(set(a) | set(b)) if key not in a or key not in b or not same(a[key], b[key])]
    report[repo_id] = {{
        "root": str(remote.root), "revision": remote.revision,
        "frames": [len(remote), len(local)], "episodes": [remote.meta.total_episodes, local.meta.total_episodes],
        "same_features": remote.meta.features == local.meta.features,
        "same_tasks": remote.meta.tasks.equals(local.meta.tasks),
        "compared": [f"{{i}}:{{key}}" for i in indices for key in local[i]],
        "image_keys": local.meta.camera_keys, "differences": differences,
    }}
print("REPORT " + json.dumps(report))
"""


def child_env(hub: HubServer, home: Path) -> dict[str, str]:
    """The environment of a user pointed at the test Hub: nothing of this machine's Hugging Face setup
    (no token file, no cache, no proxy), and no progress bars, so that stderr holds only messages."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("HF_", "HUGGINGFACE_")) and "proxy" not in k.lower()}
    env.update(HF_ENDPOINT=hub.endpoint, HF_TOKEN=TOKEN, HF_HUB_DISABLE_XET="1", HF_HOME=str(home / "hf_home"),
               HF_LEROBOT_HOME=str(home / "lerobot_home"), HF_HUB_DISABLE_TELEMETRY="1",
               HF_HUB_DISABLE_PROGRESS_BARS="1", NO_PROXY="127.0.0.1,localhost", PYTHONUNBUFFERED="1")
    return env


def run(code: str, argv: list[str], env: dict[str, str], outputs: list[str]) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True,
                            cwd=ROOT, timeout=600)
    outputs += [result.stdout, result.stderr]
    return result


def publish(dataset: Path, env: dict[str, str], outputs: list[str]) -> subprocess.CompletedProcess:
    return run(CLI, ["publish", "--dataset", str(dataset), "--repo-id", REPO_ID], env, outputs)


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.mark.slow
def test_publish_over_http_resumes_and_loads_back_with_lerobot(converted_push_buttons, tmp_path):
    from demo_factory.publish.plan import plan_publish

    plan = plan_publish(converted_push_buttons, REPO_ID)
    uploads = {upload.repo_id: upload for upload in plan.splits}
    assert len(uploads) >= 2
    first, second = list(uploads)[:2]
    outputs: list[str] = []  # every stdout and stderr of every process

    with HubServer(tmp_path / "hub", TOKEN, user=USER, tree_page_size=4) as hub:  # small pages: the client pages
        env = child_env(hub, tmp_path)

        # 1. the connection drops on the second split's first commit (its LFS objects already sent)
        hub.fail("POST", rf"^/api/datasets/{second}/commit/", status=None)
        result = publish(converted_push_buttons, env, outputs)
        assert result.returncode == 1, result.stderr
        errors = [line for line in result.stderr.splitlines() if line.strip()]
        assert "Traceback" not in result.stderr
        assert errors[-1].startswith("demo-factory publish: error: ") and second in errors[-1], errors
        assert "network error" in errors[-1] and "re-run the same command" in errors[-1]
        assert hub.repos[first].tags == {"v3.0": hub.head(first)}  # finished before the failure
        assert set(hub.files(second)) == {".gitattributes"} and not hub.repos[second].tags
        sent_before = {r.path.split("?")[0].rsplit("/", 1)[-1] for r in hub.requests if r.method == "PUT"}
        assert sent_before >= {sha256(f.source.read_bytes()) for f in uploads[second].data_files
                               if f.path.endswith(".parquet")}  # LFS objects of the failed commit

        # 2. the same command again: finishes, sending only what is missing
        mark = len(hub.requests)
        result = publish(converted_push_buttons, env, outputs)
        assert result.returncode == 0, result.stderr
        rerun = hub.requests_since(mark)
        commits = [r.path.split("/commit/")[0].removeprefix("/api/datasets/") for r in rerun
                   if r.method == "POST" and "/commit/" in r.path]
        assert first not in commits  # a finished repo is left alone
        assert set(commits) == set(uploads) - {first}
        resent = {r.path.split("?")[0].rsplit("/", 1)[-1] for r in rerun if r.method == "PUT"}
        assert not resent & {sha256(f.source.read_bytes()) for f in uploads[second].data_files}  # not sent twice
        assert "dataset files already up to date" in result.stdout

        # every split: the local files, our card and contact sheet, on main and on the v3.0 tag
        for repo_id, upload in uploads.items():
            files = hub.files(repo_id)
            expected = {f.path: f.source.read_bytes() for f in upload.data_files} | upload.card_files()
            assert set(files) == set(expected) | {".gitattributes"}, repo_id
            assert all(files[path] == data for path, data in expected.items()), repo_id
            assert hub.repos[repo_id].tags == {"v3.0": hub.head(repo_id)}
            assert not hub.repos[repo_id].private
            lfs = {path for path, blob in hub.repos[repo_id].commits[hub.head(repo_id)].files.items() if blob.lfs}
            assert {p for p in expected if p.endswith((".parquet", ".png"))} == lfs  # went through LFS

        # 3. a fresh process with an empty cache loads each split from the Hub, the same as the local one
        env_load = child_env(hub, tmp_path / "fresh")
        mark = len(hub.requests)
        result = run(LOADER, [json.dumps({r: str(u.root) for r, u in uploads.items()})], env_load, outputs)
        assert result.returncode == 0, result.stderr[-3000:]
        report = json.loads(result.stdout.split("REPORT ", 1)[1])
        for repo_id, upload in uploads.items():
            loaded = report[repo_id]
            assert loaded["revision"] == "v3.0"
            assert loaded["frames"][0] == loaded["frames"][1] > 0 and loaded["episodes"][0] == loaded["episodes"][1] > 0
            assert loaded["same_features"] and loaded["same_tasks"], loaded
            assert not loaded["differences"], loaded["differences"]
            assert any(key.endswith(tuple(loaded["image_keys"])) for key in loaded["compared"]) and loaded["image_keys"]
            snapshot = Path(loaded["root"])
            assert snapshot.is_relative_to(tmp_path / "fresh" / "lerobot_home")  # downloaded, not the local copy
            for f in upload.data_files:
                assert (snapshot / f.path).read_bytes() == f.source.read_bytes(), f.path
        downloads = hub.requests_since(mark)
        assert any(r.path.startswith("/lfs-storage/") and r.method == "GET" for r in downloads)  # LFS via the "CDN"

    # the token: on every Hub API call, never sent to the file storage, in no output or file
    api = [r for r in hub.requests if r.host.startswith("127.0.0.1") and not r.path.startswith("/lfs-storage/")]
    assert api and all(r.authorization == f"Bearer {TOKEN}" for r in api), {r.path for r in api if not r.authorization}
    storage = [r for r in hub.requests if r.path.startswith("/lfs-storage/")]
    assert storage and all(r.authorization is None and r.host.startswith("localhost") for r in storage)
    routed = [r for r in hub.requests if r.host == "huggingface.co"]  # RepoCard.validate ignores HF_ENDPOINT
    assert {r.path for r in routed} <= {"/api/validate-yaml"} and all(r.authorization is None for r in routed)
    assert all(TOKEN not in text for text in outputs)
    for path in tmp_path.rglob("*"):
        assert not path.is_file() or TOKEN.encode() not in path.read_bytes(), path


def test_a_rejected_token_ends_in_one_line_and_is_not_printed(converted_push_buttons, tmp_path):
    wrong = "hf_WrongTokenThatMustNeverAppearEither0123"
    outputs: list[str] = []
    with HubServer(tmp_path / "hub", TOKEN, user=USER) as hub:
        result = publish(converted_push_buttons, child_env(hub, tmp_path) | {"HF_TOKEN": wrong}, outputs)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    error = [line for line in result.stderr.splitlines() if line.strip()][-1]
    assert error.startswith("demo-factory publish: error: ") and "token was rejected (401)" in error, error
    assert [(r.method, r.path, r.status) for r in hub.requests] == [("GET", "/api/whoami-v2", 401)]
    assert hub.requests[0].authorization == f"Bearer {wrong}" and not hub.repos
    assert all(wrong not in text and TOKEN not in text for text in outputs)
