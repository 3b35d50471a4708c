"""`demo-factory collect-instructions`: the JSON API, the instruction file and the pictures."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from demo_factory import cli
from demo_factory.collect.pictures import (
    PICTURE_SIZE,
    SCENE_CAMERAS,
    ZOOMED_FOV_DEG,
    PictureCache,
    framed_views,
    picture_seed,
    pictures_for,
    project,
)
from demo_factory.collect.server import CollectApp, CollectServer
from demo_factory.collect.store import (
    INSTRUCTION_MAX_CHARS,
    EntryError,
    InstructionFile,
    check_instruction,
    check_writer,
    next_variation,
)
from demo_factory.instructions import load_human_instructions
from demo_factory.rollout import start_scene
from demo_factory.sim import DEFAULT_CAMERAS
from demo_factory.tasks import INSTRUCTED_TASKS, get_task
from demo_factory.tasks.palette import COLOURS


class Client:
    """A tiny JSON client for a running collection server."""

    def __init__(self, url: str):
        self.url = url.rstrip("/")

    def request(self, method: str, path: str, body=None, headers=None, raw: bytes | None = None):
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        headers = {"Content-Type": "application/json", **(headers or {})}
        request = urllib.request.Request(self.url + path, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=60) as response:
                return response.status, dict(response.headers), response.read()
        except urllib.error.HTTPError as error:
            return error.code, dict(error.headers), error.read()

    def json(self, method: str, path: str, body=None, **kwargs):
        status, _, payload = self.request(method, path, body, **kwargs)
        return status, json.loads(payload)

    def add(self, writer: str, variation_id: int, instruction: str):
        return self.json("POST", "/api/instructions",
                         {"writer": writer, "variation_id": variation_id, "instruction": instruction})


@pytest.fixture
def serve(tmp_path):
    """Start servers on free ports: ``serve(path, task)`` → (Client, InstructionFile); stopped at the end."""
    servers = []

    def start(path: Path, task_name: str = "push_buttons") -> tuple[Client, InstructionFile]:
        task = get_task(task_name)
        instructions = InstructionFile(path, task)
        server = CollectServer(CollectApp(instructions, PictureCache(task, tmp_path / "pictures")), "127.0.0.1", 0)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return Client(server.url), instructions

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()


def test_instructions_are_normalised_and_bounded():
    assert check_instruction("  press the\n green one \t first ") == "press the green one first"
    for bad in ["", "   ", "ab", "x" * (INSTRUCTION_MAX_CHARS + 1), "press\x00 it", 42, None]:
        with pytest.raises(EntryError):
            check_instruction(bad)
    assert check_writer(" w07 ") == "w07"
    for bad in ["", "a b", "<script>", "-x", "w" * 33, None, 7]:
        with pytest.raises(EntryError):
            check_writer(bad)


def test_next_variation_prefers_the_least_described_after_the_current_one():
    order = [10, 11, 12, 13]
    counts = {10: 1, 11: 0, 12: 1, 13: 0}
    assert next_variation(order, counts, done=set(), after=None, skipped=set()) == 11
    assert next_variation(order, counts, done=set(), after=11, skipped=set()) == 13
    assert next_variation(order, counts, done={13}, after=11, skipped=set()) == 12  # 11 is on screen
    assert next_variation(order, counts, done=set(), after=11, skipped={13}) == 12  # ties: next in order
    # Only skipped ones left: they come back rather than "all done".
    assert next_variation(order, counts, done={10, 11, 12}, after=None, skipped={13}) == 13
    assert next_variation(order, counts, done=set(order), after=None, skipped=set()) is None
    assert next_variation(order, {}, done=set(), after=None, skipped=set(), start=2) == 12


def test_api_appends_rows_the_converter_accepts(serve, tmp_path):
    out = tmp_path / "human.jsonl"
    client, _ = serve(out)
    status, state = client.json("GET", "/api/state?writer=w1")
    assert status == 200 and state["progress"]["with_instructions"] == 0 and state["last"] is None
    status, first = client.json("GET", "/api/next?writer=w1")
    variation = first["variation"]
    assert status == 200 and [p["url"].rsplit("/", 1)[1] for p in variation["pictures"]] == \
        ["left_shoulder.png", "right_shoulder.png", "goal.png"]

    status, answer = client.add("w1", variation["id"], "  push the dark green one,\nthen the blue one ")
    assert status == 201
    assert answer["entry"]["instruction"] == "push the dark green one, then the blue one"
    assert answer["state"]["progress"]["instructions"] == 1 and answer["state"]["progress"]["mine"] == 1
    status, after = client.json("GET", f"/api/next?writer=w1&after={variation['id']}")
    assert after["variation"]["id"] != variation["id"]

    rows = load_human_instructions(out)
    task = get_task("push_buttons")
    assert [(r.task, r.variation_id, r.words, r.author, r.language) for r in rows] == \
        [("push_buttons", variation["id"], task.variation(variation["id"]).words, "w1", "en")]
    assert json.loads(out.read_text())["colours"] == list(task.variation(variation["id"]).words)


def test_api_rejects_bad_input_and_never_echoes_markup(serve, tmp_path):
    out = tmp_path / "human.jsonl"
    client, _ = serve(out)
    vid = get_task("push_buttons").split_variations("test")[0].id
    train_vid = get_task("push_buttons").split_variations("train")[0].id
    assert client.add("w1", vid, "")[0] == 400
    assert client.add("w1", vid, "x" * (INSTRUCTION_MAX_CHARS + 1))[0] == 400
    assert client.add("<b>", vid, "press it")[0] == 400
    assert client.add("w1", train_vid, "press it")[0] == 400
    assert client.add("w1", "3", "press it")[0] == 400
    assert client.request("POST", "/api/instructions", raw=b"{not json")[0] == 400
    assert client.request("POST", "/api/instructions", raw=b"[1]")[0] == 400
    assert client.request("POST", "/api/instructions", {"writer": "w1", "variation_id": vid, "instruction": "hi there"},
                          headers={"Content-Type": "text/plain"})[0] == 415
    assert client.request("POST", "/api/instructions", raw=b"{" + b" " * 20000 + b"}")[0] == 413
    assert client.request("GET", "/api/variation/99999")[0] == 404
    assert client.request("GET", "/pictures/v1/0/../../etc/passwd")[0] == 404
    assert client.request("GET", "/api/state", headers={"Host": "evil.example:8000"})[0] == 403
    assert not out.exists()  # nothing was accepted, nothing written

    markup = "press <img src=x onerror=alert(1)> & <b>then</b> stop"
    status, headers, body = client.request("POST", "/api/instructions",
                                           {"writer": "w1", "variation_id": vid, "instruction": markup})
    assert status == 201 and headers["Content-Type"].startswith("application/json")
    assert b"<" not in body and b">" not in body  # escaped in the JSON itself
    assert json.loads(body)["entry"]["instruction"] == markup
    assert load_human_instructions(out)[0].instruction == markup
    assert client.add("w2", vid, "PRESS <img src=x onerror=alert(1)>   & <b>then</b> STOP")[0] == 409  # a duplicate
    status, headers, page = client.request("GET", "/")
    assert status == 200 and "script-src 'self'" in headers["Content-Security-Policy"]
    assert b"<script src=\"/static/app.js\"" in page
    assert b"innerHTML" not in client.request("GET", "/static/app.js")[2]


def test_concurrent_writers_never_corrupt_the_file(serve, tmp_path):
    out = tmp_path / "human.jsonl"
    client, instructions = serve(out)
    order = instructions.order
    long_text = " and then some more words" * 10  # long lines make torn writes likely if writes were not atomic

    def write(n: int) -> int:
        return client.add(f"w{n % 8}", order[n % len(order)], f"instruction number {n}{long_text}")[0]

    with ThreadPoolExecutor(16) as pool:
        assert set(pool.map(write, range(160))) == {201}
        # The same sentence from many writers at once: exactly one gets in, the others hear it is a duplicate.
        statuses = list(pool.map(lambda n: client.add(f"z{n}", order[0], "press them all")[0], range(16)))
    assert sorted(statuses) == [201] + [409] * 15
    rows = load_human_instructions(out)
    assert len(rows) == 161 and len(out.read_text().splitlines()) == 161
    assert sorted(int(r.instruction.split()[2]) for r in rows if r.instruction.startswith("instruction")) == \
        list(range(160))


def test_two_servers_can_share_one_file(tmp_path):
    """Two ``InstructionFile``s on one path stand for two server processes (one per task, say)."""
    out = tmp_path / "human.jsonl"
    servers = [InstructionFile(out, get_task("push_buttons")), InstructionFile(out, get_task("tower"))]

    def write(n: int) -> None:
        server = servers[n % 2]
        server.add(f"w{n % 4}", server.order[n % 7], f"instruction number {n}")

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(write, range(24)))
        outcomes = list(pool.map(lambda n: _try(lambda: servers[0].add(f"z{n}", servers[0].order[0], "press all")),
                                 range(8)))
    assert outcomes.count("ok") == 1
    rows = load_human_instructions(out)
    assert len(rows) == 25 and {r.task for r in rows} == {"push_buttons", "tower"}
    assert servers[0].progress()["instructions"] == 13 and servers[1].progress()["instructions"] == 12
    servers[1].add("w9", servers[1].order[3], "stack them up")  # sees push_buttons' rows written meanwhile
    assert len(load_human_instructions(out)) == 26


def _try(action) -> str:
    try:
        action()
    except EntryError:
        return "rejected"
    return "ok"


def test_a_restart_resumes_where_the_file_left_off(serve, tmp_path):
    out = tmp_path / "human.jsonl"
    out.write_text(json.dumps({"task": "tower", "colours": ["purple"], "instruction": "put purple on grey"}))  # no newline
    client, _ = serve(out)
    order = [v.id for v in get_task("push_buttons").split_variations("test")]
    done = []
    for i in range(3):
        vid = client.json("GET", "/api/next?writer=anna" + (f"&after={done[-1]}" if done else ""))[1]["variation"]["id"]
        assert client.add("anna", vid, f"press button set {i}")[0] == 201
        done.append(vid)

    restarted, _ = serve(out)  # a new server on the same file
    state = restarted.json("GET", "/api/state?writer=anna")[1]
    assert state["progress"]["instructions"] == 3 and state["progress"]["mine"] == 3
    assert state["last"]["variation_id"] == done[-1] and state["last"]["instruction"] == "press button set 2"
    seen = set()
    for _ in range(len(order) - 3):
        vid = restarted.json("GET", "/api/next?writer=anna")[1]["variation"]["id"]
        assert vid not in done and vid not in seen
        seen.add(vid)
        assert restarted.add("anna", vid, f"press button set {len(done) + len(seen)}")[0] == 201
    assert restarted.json("GET", "/api/next?writer=anna")[1]["variation"] is None  # anna has done them all
    rows = load_human_instructions(out)
    assert rows[0].task == "tower" and len(rows) == 1 + len(order)


def test_a_writer_edits_only_their_own_last_entry(serve, tmp_path):
    out = tmp_path / "human.jsonl"
    client, _ = serve(out)
    order = [v.id for v in get_task("push_buttons").split_variations("test")]
    client.add("anna", order[0], "first of anna")
    client.add("anna", order[1], "second of anna")
    client.add("ben", order[2], "first of ben")
    before = out.read_text().splitlines()

    status, answer = client.json("PUT", "/api/instructions/last", {"writer": "anna", "instruction": "second, fixed"})
    assert status == 200 and answer["entry"] == {"variation_id": order[1], "instruction": "second, fixed", "author": "anna"}
    after = out.read_text().splitlines()
    assert after[0] == before[0] and after[2] == before[2] and json.loads(after[1])["instruction"] == "second, fixed"
    assert client.json("PUT", "/api/instructions/last", {"writer": "anna", "instruction": "first of ben"})[0] == 409
    assert client.json("PUT", "/api/instructions/last", {"writer": "carl", "instruction": "anything"})[0] == 404
    assert client.json("PUT", "/api/instructions/last", {"writer": "anna", "instruction": " "})[0] == 400
    assert [r.instruction for r in load_human_instructions(out)] == ["first of anna", "second, fixed", "first of ben"]
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".partial")]


@pytest.mark.parametrize("task_name", ["push_buttons", "tower"])
def test_pictures_are_deterministic_cached_and_show_the_order(tmp_path, task_name):
    task = get_task(task_name)
    variation = max(task.split_variations("test"), key=lambda v: len(v.words))
    first, second = PictureCache(task, tmp_path / "a"), PictureCache(task, tmp_path / "b")
    for picture in pictures_for(task):
        png = first.png(variation.id, picture.name)
        assert png == second.png(variation.id, picture.name)  # same bytes from a fresh render
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (320, 320, 3)
    stamp = first.path(variation.id, "goal").stat().st_mtime_ns
    first.png(variation.id, "goal")
    assert first.path(variation.id, "goal").stat().st_mtime_ns == stamp  # served from the cache
    # The drawn goal: the colours in order (buttons left to right, cubes bottom to top).
    goal = cv2.cvtColor(cv2.imread(str(first.path(variation.id, "goal"))), cv2.COLOR_BGR2RGB).astype(int)
    centres = []
    for colour in variation.words:
        rgb = np.round(np.array(COLOURS[colour]) * 255)
        ys, xs = np.nonzero(np.abs(goal - rgb).sum(axis=-1) < 6)
        assert len(xs) > 100, colour
        centres.append(xs.mean() if task_name == "push_buttons" else -ys.mean())
    assert centres == sorted(centres)


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    def run(*argv):
        code = cli.main(["collect-instructions", "--task", "push_buttons", *argv])
        return code, capsys.readouterr().err.strip().splitlines()

    broken = tmp_path / "broken.jsonl"
    broken.write_text('{"task": "push_buttons", "instruction": "no variation"}\n')
    (tmp_path / "folder.jsonl").mkdir()
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    cases = {
        ("--out", str(broken)): "broken.jsonl:1: no variation",
        ("--out", str(tmp_path / "x.txt")): "ending in .jsonl",
        ("--out", str(tmp_path / "folder.jsonl")): "is a folder",
        ("--out", str(tmp_path / "x.jsonl"), "--split", "train"): "accepted: test",
        ("--out", str(tmp_path / "x.jsonl"), "--language", "english!"): "not a language tag",
        ("--out", str(tmp_path / "x.jsonl"), "--port", str(busy.getsockname()[1])): "already in use",
    }
    try:
        for argv, message in cases.items():
            code, err = run(*argv)
            assert code == 2 and len(err) == 1 and message in err[0], (argv, err)
    finally:
        busy.close()
    with pytest.raises(SystemExit) as exit_:
        run("--out", str(tmp_path / "x.jsonl"), "--port", "70000")
    assert exit_.value.code == 2
    assert "70000 is not a port number; accepted: 1-65535, or 0 for any free port" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.jsonl", "folder.jsonl"]  # nothing written


def test_cli_serves_until_interrupted(tmp_path):
    out = tmp_path / "sub" / "human.jsonl"
    process = subprocess.Popen(
        # Ctrl+C handled even where the suite runs in the background (`pytest &`), whose children inherit
        # SIGINT ignored: a user's interactive terminal never does that.
        [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
         "from demo_factory.cli import main; sys.exit(main())",
         "collect-instructions", "--task", "tower", "--out", str(out), "--port", "0", "--cache", str(tmp_path / "c")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        lines = [process.stdout.readline(), process.stdout.readline()]
        assert "0 instructions so far" in lines[0], lines
        url = lines[1].split()[1]
        assert url.startswith("http://127.0.0.1:")
        client = Client(url)
        vid = client.json("GET", "/api/next?writer=w1")[1]["variation"]["id"]
        assert client.add("w1", vid, "put the cubes on the grey square")[0] == 201
    finally:
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
    assert process.returncode == 0, stderr
    assert "stopped: 1 instruction for 1 of 100 variations" in stdout
    assert len(load_human_instructions(out)) == 1


OTHER_INSTRUCTED = [name for name in INSTRUCTED_TASKS if name not in ("push_buttons", "tower")]


@pytest.mark.parametrize("task_name", OTHER_INSTRUCTED)
def test_every_instructed_task_is_collected(serve, tmp_path, task_name):
    """The page serves the task's test variations; a row written there is one the converter reads; the scene
    pictures show every object the instruction names, numbered, inside the picture."""
    out = tmp_path / "human.jsonl"
    client, _ = serve(out, task_name)
    status, first = client.json("GET", "/api/next?writer=w1")
    variation = first["variation"]
    assert status == 200 and {p["url"].rsplit("/", 1)[1] for p in variation["pictures"]} >= \
        {"left_shoulder.png", "right_shoulder.png"}
    assert client.add("w1", variation["id"], "do what the pictures show")[0] == 201
    task = get_task(task_name)
    rows = load_human_instructions(out)
    assert [(r.task, r.variation_id, r.words) for r in rows] == \
        [(task_name, variation["id"], task.variation(variation["id"]).words)]

    chosen = task.variation(variation["id"])
    cameras = tuple(replace(c, fov_deg=ZOOMED_FOV_DEG) for c in DEFAULT_CAMERAS if c.name in SCENE_CAMERAS)
    world = start_scene(task, chosen, picture_seed(task, chosen), cameras, (PICTURE_SIZE, PICTURE_SIZE))
    try:
        points = task.goal_points(world, chosen)
        assert points, f"{task_name} marks no object in its pictures"
        for camera in framed_views(world, points).values():
            assert all(0 < u < PICTURE_SIZE and 0 < v < PICTURE_SIZE for u, v in (project(q, camera) for q in points))
    finally:
        world.close()


def test_a_collected_file_gives_a_task_beyond_push_buttons_its_human_split(tmp_path):
    rows = [{"task": "turn_tap", "colours": [side], "instruction": f"open the {side} hand tap", "author": "a"}
            for side in ("left", "right")]
    human = tmp_path / "human.jsonl"
    human.write_text("".join(json.dumps(row) + "\n" for row in rows))
    raw, dataset = tmp_path / "raw", tmp_path / "dataset"
    assert cli.main(["generate", "--task", "turn_tap", "--split", "test", "--episodes", "2", "--image-size", "32",
                     "--workers", "1", "--out", str(raw)]) == 0
    assert cli.main(["convert", "--in", str(raw), "--out", str(dataset), "--human-instructions", str(human)]) == 0
    provenance = json.loads((dataset / "test_unseen_human" / "meta" / "demo_factory.json").read_text())
    assert sorted(e["instruction"] for e in provenance["episodes"]) == ["open the left hand tap",
                                                                       "open the right hand tap"]
