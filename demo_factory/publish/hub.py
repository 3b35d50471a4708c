"""Pushing a ``PublishPlan`` to the Hugging Face Hub, resumably.

Per split repo, in this order:

1. list the repo's files (``list_repo_tree``) and compare each local file with its remote
   counterpart: same size and same content hash (sha256 for LFS files, git blob sha1 otherwise);
2. the missing or different dataset files go up with LeRobot's own ``LeRobotDataset.push_to_hub``
   (``allow_patterns`` = exactly those files; it creates the repo, uploads in one commit and pushes
   LeRobot's generic card);
3. our card (``README.md``) and ``contact_sheet.png`` replace LeRobot's card in one commit;
4. the ``v3.0`` tag LeRobot's loader looks for is (re)placed on the repo's last commit.

Each step's result is visible remotely, so a run that stops anywhere (network, quota, Ctrl-C) is
finished by running the same command again: finished repos are left alone, a partly published one
gets only its missing files, its card and its tag. An upload commit is atomic; LFS blobs sent before
a failed commit are already on the Hub and are not sent again.
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field

from httpx import TransportError
from huggingface_hub import CommitOperationAdd, HfApi, get_token
from huggingface_hub.errors import HfHubHTTPError, RepositoryNotFoundError, RevisionNotFoundError
from huggingface_hub.utils.sha import git_hash

from demo_factory.publish.plan import EXIT_HUB, LocalFile, PublishError, PublishPlan, SplitUpload, human_size

TAG = "v3.0"  # lerobot.datasets.lerobot_dataset.CODEBASE_VERSION, the revision LeRobot's loader downloads
LICENSE = "apache-2.0"
TAGS = ["demo-factory", "simulation", "language-conditioned"]  # LeRobot's card adds "LeRobot"
BRANCH = "main"


@dataclass
class RepoReport:
    repo_id: str
    uploaded: list[str] = field(default_factory=list)  # dataset files sent this run
    uploaded_bytes: int = 0
    card: list[str] = field(default_factory=list)  # card files sent this run
    tagged: bool = False
    created: bool = False


@dataclass
class PublishReport:
    user: str
    repos: list[RepoReport]


def _same(content_size: int, sha256: Callable[[], str], blob: Callable[[], str], remote) -> bool:
    """Whether a local file equals a remote ``RepoFile`` (None: absent)."""
    if remote is None or getattr(remote, "size", None) != content_size:
        return False
    lfs = getattr(remote, "lfs", None)
    if lfs:
        return lfs["sha256"] == sha256()
    return remote.blob_id == blob()


def _file_sha256(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def same_file(local: LocalFile, remote) -> bool:
    return _same(local.size, lambda: _file_sha256(local.source), lambda: git_hash(local.source.read_bytes()), remote)


def same_bytes(content: bytes, remote) -> bool:
    return _same(len(content), lambda: hashlib.sha256(content).hexdigest(), lambda: git_hash(content), remote)


def scrub(text: str, secrets: list[str]) -> str:
    """``text`` on one line with every secret (the token) replaced."""
    for secret in secrets:
        if secret:
            text = text.replace(secret, "***")
    return " ".join(text.split())


def _remote_files(api: HfApi, repo_id: str) -> dict | None:
    """Repo path → RepoFile on the main branch; None when the repo does not exist (or is not visible)."""
    try:
        entries = api.list_repo_tree(repo_id, repo_type="dataset", recursive=True)
        return {e.path: e for e in entries if hasattr(e, "blob_id")}
    except RepositoryNotFoundError:
        return None


def _check_owner(repo_id: str, identity: dict) -> None:
    owner = repo_id.split("/")[0]
    namespaces = [identity.get("name")] + [o.get("name") for o in identity.get("orgs", [])]
    if owner not in namespaces:
        raise PublishError(f"--repo-id {repo_id}: the namespace {owner!r} is not yours; the token belongs to "
                           f"{identity.get('name')!r} (organisations: {', '.join(namespaces[1:]) or 'none'})", EXIT_HUB)


def _escape(path: str) -> str:
    """An fnmatch pattern matching exactly ``path`` (allow_patterns are fnmatch patterns)."""
    return "".join(f"[{c}]" if c in "*?[]" else c for c in path)


def _push_data(upload: SplitUpload, missing: list[LocalFile], private: bool) -> None:
    """LeRobot's own upload of the missing dataset files (creates the repo when needed)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(upload.repo_id, root=upload.root)  # reads the local split only
    dataset.push_to_hub(tags=TAGS, license=LICENSE, private=private, tag_version=False,
                        allow_patterns=[_escape(f.path) for f in missing])


def _push_split(api: HfApi, upload: SplitUpload, private: bool, log: Callable[[str], None]) -> RepoReport:
    report = RepoReport(upload.repo_id)
    remote = _remote_files(api, upload.repo_id)
    if remote is None:
        report.created = True
        remote = {}
    elif private and not api.repo_info(upload.repo_id, repo_type="dataset").private:
        api.update_repo_settings(upload.repo_id, private=True, repo_type="dataset")
        log(f"{upload.repo_id}: made private (--private)")
    missing = [f for f in upload.data_files if not same_file(f, remote.get(f.path))]
    if report.created or missing:
        size = sum(f.size for f in missing)
        log(f"{upload.repo_id}: uploading {len(missing)} of {len(upload.data_files)} dataset files ({human_size(size)})")
        _push_data(upload, missing, private)
        report.uploaded, report.uploaded_bytes = [f.path for f in missing], size
    card = {name: content for name, content in upload.card_files().items()
            if report.uploaded or not same_bytes(content, remote.get(name))}  # LeRobot's push replaced README.md
    if card:
        api.create_commit(upload.repo_id, repo_type="dataset", commit_message="Dataset card (demo-factory)",
                          operations=[CommitOperationAdd(path_in_repo=n, path_or_fileobj=c) for n, c in card.items()])
        report.card = sorted(card)
    refs = api.list_repo_refs(upload.repo_id, repo_type="dataset")
    head = next(b.target_commit for b in refs.branches if b.name == BRANCH)
    tagged = next((t.target_commit for t in refs.tags if t.name == TAG), None)
    if tagged != head:
        if tagged is not None:
            with contextlib.suppress(RevisionNotFoundError):
                api.delete_tag(upload.repo_id, tag=TAG, repo_type="dataset")
        api.create_tag(upload.repo_id, tag=TAG, revision=BRANCH, repo_type="dataset")
        report.tagged = True
    return report


def publish(plan: PublishPlan, log: Callable[[str], None] = print) -> PublishReport:
    """Publish every split of ``plan``; ``PublishError`` (exit code 1) for credential and Hub problems."""
    token = get_token()
    if not token:
        raise PublishError("no Hugging Face token: run `huggingface-cli login` (or `hf auth login`) or set HF_TOKEN", EXIT_HUB)
    api = HfApi()
    repo = "the Hub"
    try:
        identity = api.whoami()
        _check_owner(plan.repo_id, identity)
        reports = []
        for upload in plan.splits:
            repo = upload.repo_id
            reports.append(_push_split(api, upload, plan.private, log))
        return PublishReport(identity.get("name", "?"), reports)
    except PublishError:
        raise
    except HfHubHTTPError as exc:  # the Hub answered with an error (huggingface_hub >= 1: never requests')
        status = exc.response.status_code if exc.response is not None else None
        why = {401: "the Hugging Face token was rejected (401): log in again with `huggingface-cli login` or fix HF_TOKEN",
               403: "not allowed to write (403): the repo belongs to someone else or the token has no write access"}
        message = why.get(status, f"the Hub answered {status or 'an error'}: {exc}")
        raise PublishError(scrub(f"{repo}: {message}; nothing further was sent, re-run the same command to "
                                 "finish once fixed", [token]), EXIT_HUB) from None
    except (OSError, TransportError) as exc:  # no answer: httpx's connection, timeout and protocol errors
        reason = scrub(str(exc), [token])
        reason = reason if len(reason) <= 160 else reason[:160] + "…"
        raise PublishError(scrub(f"{repo}: network error ({type(exc).__name__}: {reason}); re-run the same command "
                                 "to resume: only what is missing is uploaded", [token]), EXIT_HUB) from None
