"""`demo-factory publish` against an in-memory Hub: repos, files, tags, card, token hygiene, dry run, resume.

The Hub client is replaced by ``FakeHub`` at the two places the code makes one (LeRobot's
``push_to_hub`` and ``demo_factory.publish.hub``), and LeRobot's card push is recorded, so the real
publishing code (ours and LeRobot's) runs; every socket connection fails the test.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import shutil
import socket
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
import requests
from huggingface_hub import DatasetCard
from huggingface_hub.errors import RepositoryNotFoundError, RevisionNotFoundError
from huggingface_hub.hf_api import RepoFile
from huggingface_hub.utils import filter_repo_objects
from huggingface_hub.utils.sha import git_hash

from demo_factory.cli_common import run_command
from demo_factory.convert import DATASET_SPLITS
from demo_factory.publish.cli import add_parser

TOKEN = "hf_TestTokenThatMustNeverAppear0123456789"
USER = "me"
LFS_SUFFIXES = (".parquet", ".png")  # stored through LFS by the Hub's default .gitattributes


class FakeHub:
    """Dataset repos in memory: files, commits, tags; every call recorded as (method, repo_id, detail)."""

    def __init__(self):
        self.repos: dict[str, dict] = {}
        self.calls: list[tuple[str, str, object]] = []
        self.fail_upload: set[str] = set()  # repos whose next upload_folder loses the connection
        self._commits = itertools.count(1)

    def commit(self, repo_id: str, files: dict[str, bytes]) -> None:
        repo = self.repos[repo_id]
        repo["files"].update(files)
        repo["head"] = f"commit{next(self._commits)}"

    def tree(self, repo_id: str) -> dict[str, bytes]:
        return self.repos[repo_id]["files"]

    def calls_of(self, method: str) -> list[tuple[str, object]]:
        return [(repo, detail) for m, repo, detail in self.calls if m == method]

    def api(self):
        hub = self

        class Api:
            def __init__(self, *args, **kwargs):
                pass

            def whoami(self, token=None):
                hub.calls.append(("whoami", "", None))
                return {"name": USER, "orgs": [{"name": "my-lab"}]}

            def _repo(self, repo_id):
                if repo_id not in hub.repos:
                    raise hub_error(RepositoryNotFoundError, f"{repo_id} not found")
                return hub.repos[repo_id]

            def create_repo(self, repo_id, private=False, repo_type=None, exist_ok=False, **kwargs):
                hub.calls.append(("create_repo", repo_id, private))
                hub.repos.setdefault(repo_id, {"files": {}, "tags": {}, "head": "empty", "private": private})

            def repo_info(self, repo_id, repo_type=None, **kwargs):
                return SimpleNamespace(private=self._repo(repo_id)["private"])

            def update_repo_settings(self, repo_id, private=None, repo_type=None, **kwargs):
                hub.calls.append(("update_repo_settings", repo_id, private))
                self._repo(repo_id)["private"] = private

            def list_repo_tree(self, repo_id, repo_type=None, recursive=False, **kwargs):
                for path, data in self._repo(repo_id)["files"].items():
                    lfs = ({"size": len(data), "oid": hashlib.sha256(data).hexdigest(), "pointerSize": 130}
                           if path.endswith(LFS_SUFFIXES) else None)
                    yield RepoFile(path=path, size=len(data), oid=git_hash(b"pointer" if lfs else data), lfs=lfs)

            def upload_folder(self, repo_id, folder_path, repo_type=None, revision=None, allow_patterns=None,
                              ignore_patterns=None, **kwargs):
                self._repo(repo_id)
                if repo_id in hub.fail_upload:
                    hub.fail_upload.discard(repo_id)
                    raise requests.ConnectionError(f"Connection reset while uploading to {repo_id}")
                root = Path(folder_path)
                paths = [p.relative_to(root).as_posix() for p in sorted(root.rglob("*")) if p.is_file()]
                ignore = [f"{p}*" if p.endswith("/") else p for p in ignore_patterns or []]
                chosen = list(filter_repo_objects(paths, allow_patterns=allow_patterns, ignore_patterns=ignore))
                hub.calls.append(("upload_folder", repo_id, chosen))
                hub.commit(repo_id, {p: (root / p).read_bytes() for p in chosen})

            def create_commit(self, repo_id, operations, commit_message=None, repo_type=None, **kwargs):
                self._repo(repo_id)
                files = {op.path_in_repo: op.path_or_fileobj for op in operations}
                hub.calls.append(("create_commit", repo_id, sorted(files)))
                hub.commit(repo_id, files)

            def list_repo_refs(self, repo_id, repo_type=None, **kwargs):
                repo = self._repo(repo_id)
                return SimpleNamespace(branches=[SimpleNamespace(name="main", target_commit=repo["head"])],
                                       tags=[SimpleNamespace(name=t, target_commit=c) for t, c in repo["tags"].items()])

            def delete_tag(self, repo_id, tag, repo_type=None, **kwargs):
                hub.calls.append(("delete_tag", repo_id, tag))
                if self._repo(repo_id)["tags"].pop(tag, None) is None:
                    raise hub_error(RevisionNotFoundError, f"no tag {tag}")

            def create_tag(self, repo_id, tag, revision=None, repo_type=None, **kwargs):
                hub.calls.append(("create_tag", repo_id, tag))
                repo = self._repo(repo_id)
                repo["tags"][tag] = repo["head"]

        return Api


def hub_error(kind, message: str):
    """A Hub error as huggingface_hub raises it (with the HTTP response it came from)."""
    return kind(message, response=httpx.Response(404, request=httpx.Request("GET", "https://hub.test")))


@pytest.fixture
def hub(monkeypatch, tmp_path):
    """A fake Hub wired in, a token in the environment, no token file, and no socket may connect."""
    fake = FakeHub()
    monkeypatch.setattr("lerobot.datasets.lerobot_dataset.HfApi", fake.api())
    monkeypatch.setattr("demo_factory.publish.hub.HfApi", fake.api())

    def push_card(card, repo_id, repo_type=None, revision=None, **kwargs):
        fake.calls.append(("card.push_to_hub", repo_id, None))
        fake.commit(repo_id, {"README.md": str(card).encode()})

    monkeypatch.setattr(DatasetCard, "push_to_hub", push_card)
    monkeypatch.setenv("HF_TOKEN", TOKEN)
    monkeypatch.setattr("huggingface_hub.constants.HF_TOKEN_PATH", str(tmp_path / "no_token"))
    return fake


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a test of publish tried to open a network connection")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def publish(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="demo-factory")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["publish", *map(str, argv)])
    return run_command(args)


def split_names(dataset: Path) -> list[str]:
    return sorted(p.name for p in dataset.iterdir() if (p / "meta" / "info.json").is_file())


def local_files(split_root: Path) -> set[str]:
    return {p.relative_to(split_root).as_posix() for p in split_root.rglob("*")
            if p.is_file() and p.relative_to(split_root).parts[0] != "images"}


def test_publish_creates_one_tagged_repo_per_split_in_lerobot_layout(hub, converted_push_buttons, tmp_path, capsys):
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb", "--private") == 0
    splits = split_names(converted_push_buttons)
    repos = [f"me/pb_{s}" for s in splits]
    assert sorted(hub.repos) == sorted(repos)
    assert {repo for repo, _ in hub.calls_of("create_repo")} == set(repos)
    assert all(private for _, private in hub.calls_of("create_repo"))
    for split in splits:
        repo = hub.repos[f"me/pb_{split}"]
        assert set(repo["files"]) == local_files(converted_push_buttons / split) | {"README.md", "contact_sheet.png"}
        assert repo["tags"] == {"v3.0": repo["head"]}  # the loader's revision holds the final card
        card = DatasetCard(repo["files"]["README.md"].decode())
        assert card.data.configs == [{"config_name": "default", "data_files": [{"split": split, "path": "data/*/*.parquet"}]}]
        assert f"# me/pb_{split}:" in card.text
        for other in splits:
            if other != split:
                assert f"https://huggingface.co/datasets/me/pb_{other}" in card.text
        assert 'D("me/pb_' + split + '")' in card.text and "--dataset.root" not in card.text

    # the files of a repo are a LeRobot dataset by themselves (what the loader downloads at v3.0)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    download = tmp_path / "download"
    for path, data in hub.tree("me/pb_train").items():
        (download / path).parent.mkdir(parents=True, exist_ok=True)
        (download / path).write_bytes(data)
    remote = LeRobotDataset("me/pb_train", root=download)
    local = LeRobotDataset("me/pb_train", root=converted_push_buttons / "train")
    assert len(remote) == len(local) > 0 and remote[0]["task"] == local[0]["task"]
    out = capsys.readouterr().out
    assert "https://huggingface.co/datasets/me/pb_train" in out


def test_rerun_after_publishing_sends_nothing(hub, converted_push_buttons):
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 0
    hub.calls.clear()
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 0
    assert not [c for c in hub.calls if c[0] not in ("whoami",)]


def test_upload_failure_midway_is_reported_and_a_rerun_finishes_only_the_missing_part(hub, converted_push_buttons, capsys):
    splits = split_names(converted_push_buttons)
    order = [s for s in DATASET_SPLITS if s in splits]  # the order publish goes through them
    broken = f"me/pb_{order[1]}"
    hub.fail_upload.add(broken)
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and broken in err[0] and "re-run" in err[0]
    assert hub.repos["me/pb_train"]["tags"]  # finished before the failure
    assert not hub.repos[broken]["files"] and not hub.repos[broken]["tags"]

    # a split half-way: one dataset file lost and LeRobot's generic card instead of ours
    train = hub.repos["me/pb_train"]["files"]
    del train["meta/stats.json"]
    train["README.md"] = b"---\nlicense: apache-2.0\n---\ngeneric\n"
    hub.calls.clear()
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 0
    uploads = dict(hub.calls_of("upload_folder"))
    assert uploads["me/pb_train"] == ["meta/stats.json"]
    assert sorted(uploads[broken]) == sorted(local_files(converted_push_buttons / order[1]))
    assert set(uploads) == {"me/pb_train", *(f"me/pb_{s}" for s in order[1:])}
    for split in order:
        repo = hub.repos[f"me/pb_{split}"]
        assert set(repo["files"]) == local_files(converted_push_buttons / split) | {"README.md", "contact_sheet.png"}
        assert repo["tags"] == {"v3.0": repo["head"]}
        assert repo["files"]["README.md"].startswith(b"---\nlicense: apache-2.0\ntask_categories")


def test_token_appears_in_no_output_or_file(hub, converted_push_buttons, tmp_path, capsys, monkeypatch):
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 0
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb", "--dry-run") == 0

    def leaky_whoami(self, token=None):  # an error message that quotes the token must not show it
        raise requests.ConnectionError(f"proxy refused Authorization: Bearer {TOKEN}")

    monkeypatch.setattr("demo_factory.publish.hub.HfApi", type("Leaky", (hub.api(),), {"whoami": leaky_whoami}))
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 1
    captured = capsys.readouterr()
    assert "***" in captured.err
    assert TOKEN not in captured.out + captured.err
    for repo in hub.repos.values():
        assert all(TOKEN.encode() not in data for data in repo["files"].values())
    for folder in (converted_push_buttons, tmp_path):
        for path in folder.rglob("*"):
            assert not path.is_file() or TOKEN.encode() not in path.read_bytes(), path


def test_dry_run_lists_repos_files_size_and_card_without_network(converted_push_buttons, capsys, monkeypatch):
    def no_hub(*args, **kwargs):
        raise AssertionError("dry run made a Hub client")

    monkeypatch.setattr("huggingface_hub.HfApi.__init__", no_hub)
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb", "--dry-run") == 0
    out = capsys.readouterr().out
    for split in split_names(converted_push_buttons):
        assert f"me/pb_{split}" in out
        for path in local_files(converted_push_buttons / split):
            assert path in out
    assert "total: " in out and "contact_sheet.png" in out
    assert "task_categories:" in out and "## Limitations" in out


@pytest.mark.parametrize(("argv", "expected"), [
    (["--repo-id", "someone-else/pb"], "'someone-else' is not yours"),
    (["--repo-id", "no-owner"], "'no-owner' is not a Hub repo id"),
    (["--repo-id", "me/bad name"], "'me/bad name' is not a Hub repo id"),
])
def test_bad_repo_ids_end_in_one_line(hub, converted_push_buttons, capsys, argv, expected):
    code = publish("--dataset", converted_push_buttons, *argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code in (1, 2) and len(err) == 1 and expected in err[0]
    assert not hub.repos


def test_missing_credentials_and_missing_dataset(hub, converted_push_buttons, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("HF_TOKEN")
    assert publish("--dataset", converted_push_buttons, "--repo-id", "me/pb") == 1
    assert "no Hugging Face token" in capsys.readouterr().err
    assert publish("--dataset", tmp_path / "nowhere", "--repo-id", "me/pb") == 2
    assert "nowhere is not a folder" in capsys.readouterr().err
    cardless = tmp_path / "cardless"
    shutil.copytree(converted_push_buttons / "train", cardless / "train")
    assert publish("--dataset", cardless, "--repo-id", "me/pb", "--dry-run") == 2
    assert "no dataset card README.md" in capsys.readouterr().err
    assert not hub.repos
