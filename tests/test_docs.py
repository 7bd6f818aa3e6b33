"""Every command line the docs show works: each one in a shell block of README.md and docs/*.md is run
here as a subprocess, as a reader would type it in a checkout (or in the documented short form the
table below gives, with its reason), and must exit 0 and leave the files it names (--json, --out,
--bvh, --report, --dump, ...). A command that cannot run here (real hardware, root on a board, 100
minutes of training) is listed in NOT_RUNNABLE with the reason. A command in the docs that is in
neither table fails the test, and so does an entry no doc shows any more: new docs cannot slip through.

Shell blocks: fenced with ```bash, ```sh, ```shell, ```console (lines after a `$ ` prompt), or with no
language when the block's first command starts with a program (edge, python, .venv/bin/..., ./scripts/...,
sudo, ...); diagrams, config files and udev rules in plain fences are not commands. `\\` continuations
are joined and `#` comments dropped. Commands on `../shared/mocap` skip when the data is absent.
"""
import ast
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.conftest import MOCAP

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL_LANGUAGES = {"bash", "sh", "shell", "console"}
# A plain fence holds commands when its first command starts with one of these programs.
PROGRAMS = re.compile(r"^(edge|python3?|pip|sudo|torchrun|i2cdetect|systemctl|journalctl|raspi-config|git|"
                      r"(\.{0,2}/|\.venv/|scripts/)\S+)$")


@dataclass
class Short:
    """How a documented command runs here: `replace` each key by its value in the command text, then
    append `add` (argparse keeps the last of a repeated flag, so `--seconds 2` after `--seconds 600`
    wins); `why` says what the short form leaves out."""
    why: str
    add: str = ""
    replace: dict = field(default_factory=dict)


# The command as the docs show it (comments dropped, continuations joined, quotes as the shell removes
# them) -> how it runs here.
RUN = {
    "./scripts/demo": Short(
        "its set-up half (make .venv, pip install -e .) is what ./scripts/test runs before this test; its "
        "replay line, read from the script, runs here for 2 s at full speed instead of 16 s in real time",
        add="--seconds 2 --speed max"),
    ".venv/bin/edge eval --data ../shared/mocap --split val --json out/val.json": Short(
        "an even spread of 60 val clips, 90 frames each (30 scored after the 1 s warm-up): seconds instead "
        "of minutes", add="--max-frames 90 --max-clips 60"),
    ".venv/bin/edge replay samples/cmu_09_12_walk.session.npz --vmc 192.168.1.20:39539 --vrchat 192.168.1.20:9000 "
    "--json out/replay.json": Short(
        "the receivers on this machine (the docs' PC address may have no route here); 2 s at full speed",
        add="--seconds 2 --speed max", replace={"192.168.1.20": "127.0.0.1"}),
    "sudo -u edgepose /opt/edgepose/venv/bin/python -m edge.native": Short(
        "the board's edgepose user and /opt venv do not exist here: the same module from this venv",
        replace={"sudo -u edgepose /opt/edgepose/venv/bin/python": "python"}),
    "sudo /opt/edgepose/venv/bin/edge profile --cpu-quota 0.25 --hz 60 --samples auto --frames 3600 "
    "--json profile.json": Short(
        "this venv's edge (root in CI already; without root it says the quota was not enforced); the "
        "ladder up to N=2 with 20-frame probes and a 60-frame run instead of up to N=128 and 3,600 frames",
        add="--max-samples 2 --probe-frames 20 --frames 60",
        replace={"sudo /opt/edgepose/venv/bin/edge": "edge"}),
    "sudo /opt/edgepose/venv/bin/edge profile --samples 128 --adaptive --frames 4200 --hog-at 15 --hog-seconds 30 "
    "--hog-procs 5 --json hog.json": Short(
        "this venv's edge; N=8 for 180 frames with a 1 s one-process hog after 1 s, instead of N=128 for "
        "70 s with a 30 s five-process hog",
        add="--samples 8 --frames 180 --hog-at 1 --hog-seconds 1 --hog-procs 1",
        replace={"sudo /opt/edgepose/venv/bin/edge": "edge"}),
}

BOARD = "examples/board.toml names the board's UART (/dev/ttyAMA0), I2C bus 1 and can0"
TRAIN = "trains for about 100 minutes and overwrites the shipped models/ (tests/test_train_ddp.py trains briefly)"
NOT_RUNNABLE = {
    ".venv/bin/edge soak --minutes 120 --source ../shared/mocap/cmu_fbx_daz/144/144_04.bvh "
    "../shared/mocap/cmu_fbx_daz/55/55_27.bvh --json out/soak.json --plot docs/img/soak.png":
        "two hours of real time; tests/test_soak.py runs a minute of it with the same checks",
    "/opt/edgepose/venv/bin/pip install edgepose[headset]": "the board's install under /opt; the test extra "
                                                             "pulls the [headset] extra in (./scripts/test)",
    ".venv/bin/pip install -e .[headset]": "the test extra already installs the [headset] extra (./scripts/test)",
    "sudo apt-get install adb": "installs a system package on the board (root)",
    "adb devices": "needs a headset on USB with developer mode; tests/test_webxr_browser.py uses an emulated one",
    "adb reverse tcp:8080 tcp:8080": "needs a headset on USB with developer mode; the tls=0 loopback link it "
                                     "serves is what tests/test_webxr_source.py talks to",
    "./scripts/test": "the test suite itself (.ci/run calls it)",
    "edge calibrate --config examples/board.toml --out calibration.json":
        f"{BOARD}; tests/test_cli.py runs edge calibrate on simulated devices",
    "edge run --config examples/board.toml":
        f"{BOARD}, and runs until Ctrl-C; tests/test_cli.py runs edge run on a pty headset",
    "edge listen /dev/ttyUSB0": "a USB serial adapter on the pose stream; tests/test_cli.py runs edge listen on a pty",
    ".venv/bin/pip install -e .[train]": "installs PyTorch; CI does it (EDGEPOSE_EXTRAS=train ./scripts/test)",
    ".venv/bin/python -m motion.pack": "reads all of ../shared/mocap (3 min) and writes the 51 MiB pack; "
                                       "tests/test_train_device.py builds and checks a pack of five clips",
    "scripts/train-device --minutes 9 --sizes 256 --cmu-width 256 -- --batch 1024":
        "needs an accelerator (the device tool) and the pack; tests/test_train_device.py runs it on CPU at a "
        "tiny size, the CMU-only run beside it included",
    "scripts/train-device --minutes 4 --sizes 256 --resume DIR -- --lr 3e-4":
        "needs an accelerator and an earlier run; tests/test_train_device.py resumes a tiny CPU run",
    ".venv/bin/python -m models.train --data .cache/pack/edgepose-pack.npz --hidden 256 --minutes 95": TRAIN,
    ".venv/bin/python -m models.train --data ../shared/mocap --sources cmu daz hdm05": TRAIN,
    ".venv/bin/python -m models.train --data ../shared/mocap --device cuda": "needs a CUDA GPU; " + TRAIN,
    ".venv/bin/python -m models.train_upper --ckpt .cache/train --minutes 24 --arms-from-ik --out .cache/train_upper --export models":
        "trains the upper-body head for 24 minutes on a trained CVAE's folder and overwrites the shipped "
        "models/ (tests/test_models.py checks the head it exports)",
    ".venv/bin/torchrun --nproc_per_node=4 -m models.train --data DATA": "needs 4 GPUs; " + TRAIN,
    ".venv/bin/python -m models.train --data ../shared/mocap --device cpu --threads 2 --workers 1 --hidden 256 "
    "--init models/checkpoints --best-of 8 --winner-grad --eps 0.02 --clearance 10000 --lr 3e-4 --windows-by sqrt "
    "--mirror 0.5 --tempo 0.8,1.25 --val-every 100 --no-export --minutes 45 --ckpt .cache/runs/v06 "
    "--out .cache/runs/v06": "trains for 45 minutes on both cores (tests/test_train_recipe.py and test_augment.py "
                             "check its parts)",
    ".venv/bin/python -m models.train --data ../shared/mocap --device cpu --threads 2 --hidden 256 --best-of 8 "
    "--winner-grad --eps 0.02 --clearance 10000 --lr 2e-4 --windows-by sqrt --mirror 0.5 --tempo 0.8,1.25 "
    "--no-export --minutes 45 --resume .cache/runs/v06 --ckpt .cache/runs/v06b --out .cache/runs/v06b":
        "continues a 45-minute run from the one above",
    "python bench/train_step.py --best-of 16,8,4 --threads 1,2": "reads all of train (3 min of retargeting on a "
                                                                  "fresh machine), then a minute a recipe",
    "python bench/train_step.py --best-of 8 --threads 1,2 --precision fp32,bf16 --winner only":
        "reads all of train, then a minute a setting; bf16 needs a CPU with AVX-512 BF16 or AMX to be fast",
    "python -m motion.conventions": "reads all of train (3 min of retargeting on a fresh machine); "
                                    "tests/test_conventions.py checks the measurement",
    "scripts/eval-checkpoint .cache/runs/v06 .cache/models/v06": "needs the run above's checkpoint; exports, "
                                                                  "quantizes and evaluates for about 10 minutes",
    ".venv/bin/python -m models.validate .cache/runs/v06 --conventions in": "needs the run above's checkpoint; "
                                                                            "reads val's clips (a minute)",
    ".venv/bin/python -m quantize": "rebuilds the shipped models/*.int8.onnx in place (minutes); "
                                    "tests/test_quantize.py checks the builds",
    "sudo apt install python3-venv i2c-tools gcc libc6-dev": "installs system packages on the board (root)",
    "sudo useradd --system --home /var/lib/edgepose --create-home --groups dialout,i2c edgepose":
        "creates a system user on the board (root)",
    "sudo python3 -m venv /opt/edgepose/venv": "the board's install under /opt (root)",
    "sudo /opt/edgepose/venv/bin/pip install /path/to/edgepose": "the board's install under /opt (root)",
    "sudo mkdir -p /etc/edgepose && sudo cp examples/board.toml /etc/edgepose/board.toml":
        "writes the board's /etc (root)",
    "sudo raspi-config nonint do_serial_cons 1": "Raspberry Pi OS only: turns the serial console off",
    "sudo raspi-config nonint do_i2c 0": "Raspberry Pi OS only: turns I2C on",
    "i2cdetect -y 1": "needs the board's I2C bus 1 and a BNO055 on it",
    "sudo systemctl daemon-reload": "systemd on the board (root)",
    "sudo -u edgepose /opt/edgepose/venv/bin/edge calibrate --config /etc/edgepose/board.toml "
    "--out /var/lib/edgepose/calibration.json": f"the board's install, {BOARD}",
    "sudo systemctl enable --now edgepose": "starts the board's service under systemd (root)",
    "journalctl -u edgepose -f": "follows the board's systemd journal until Ctrl-C",
    "sudo scripts/arm64-check": "root: builds an arm64 Debian and runs it under QEMU (10 minutes, then 5-9 a CPU); "
                                "not in CI",
    "sudo scripts/arm64-insns": "root, QEMU and the rootfs scripts/arm64-check builds; not in CI",
    ".venv/bin/python bench/arm64/frame_insns.py --report out/arm64-insns":
        "reads the counts sudo scripts/arm64-insns writes; tests/test_arm64_insns.py runs the report on counts "
        "it writes",
}

# Flags whose value is a file or folder the command writes; a report folder must hold index.html.
OUTPUT_FLAGS = {"--json", "--out", "--bvh", "--report", "--dump", "--record", "--pose-log"}


def shell_blocks(text):
    """(first line number, [(line number, line)]) of each fenced block that holds shell commands."""
    blocks, lines = [], text.splitlines()
    k = 0
    while k < len(lines):
        fence = re.match(r"^\s*```\s*([\w+-]*)", lines[k])
        if not fence:
            k += 1
            continue
        language, body = fence.group(1).lower(), []
        k += 1
        while k < len(lines) and not lines[k].lstrip().startswith("```"):
            body.append((k + 1, lines[k]))
            k += 1
        k += 1
        if language == "console":
            body = [(n, line.split("$ ", 1)[1]) for n, line in body if line.lstrip().startswith("$ ")]
        elif language == "":
            first = next((line.split()[0] for _, line in body if line.strip() and not line.lstrip().startswith("#")), "")
            if not PROGRAMS.match(first):
                continue
        elif language not in SHELL_LANGUAGES:
            continue
        blocks.append(body)
    return blocks


def commands_in(text):
    """(line number, command) for every command in the text's shell blocks, `\\` continuations joined,
    `#` comments dropped, words as the shell splits them, joined by one space."""
    out = []
    for body in shell_blocks(text):
        pending, start = "", None
        for number, line in body:
            start = start or number
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            words = shlex.split(pending + line, comments=True)
            if words:
                out.append((start, " ".join(words)))
            pending, start = "", None
    return out


def doc_commands():
    """{command: "file:line"} over README.md and docs/*.md."""
    found = {}
    for doc in DOCS:
        for number, command in commands_in(doc.read_text()):
            found.setdefault(command, f"{doc.relative_to(ROOT)}:{number}")
    return found


def demo_command():
    """The replay line scripts/demo runs (its last line, before the "$@" it passes on)."""
    line = [ln for ln in (ROOT / "scripts" / "demo").read_text().splitlines() if ln.strip()][-1]
    assert line.startswith(".venv/bin/edge replay") and line.endswith('"$@"'), f"scripts/demo changed: {line!r}"
    return line[:-len('"$@"')].strip()


def program(word):
    """This venv's program for the docs' `edge` / `python` (bare, or from .venv/bin/)."""
    name = word.rsplit("/", 1)[-1]
    if word not in (name, f".venv/bin/{name}") or name not in ("edge", "python", "python3"):
        raise AssertionError(f"no mapping for the program {word!r}: add a replace= to its Short")
    if name == "edge":
        script = Path(sys.executable).with_name("edge")
        return [str(script)] if script.exists() else [sys.executable, "-m", "edgecli"]
    return [sys.executable]


def runnable(command):
    """The argv that runs the documented command here (its short form)."""
    short = RUN[command]
    text = demo_command() if command == "./scripts/demo" else command
    for old, new in short.replace.items():
        assert old in text, f"{command!r}: {old!r} is not in it"
        text = text.replace(old, new)
    words = shlex.split(text) + shlex.split(short.add)
    return program(words[0]) + words[1:], words


def checkout_view(folder):
    """A folder that looks like this checkout from inside (each top-level entry a symlink to the real
    one) with a fresh out/, and ../shared/mocap beside it when the data is here, so the docs' relative
    paths resolve and what the commands write stays in `folder`."""
    view = folder / "edgepose"
    view.mkdir()
    for entry in ROOT.iterdir():
        if entry.name not in ("out", ".git", ".pytest_cache"):
            (view / entry.name).symlink_to(entry)
    if MOCAP.exists():
        (folder / "shared").mkdir()
        (folder / "shared" / "mocap").symlink_to(MOCAP)
    return view


def test_the_docs_have_commands_and_the_parser_finds_each_kind():
    found = doc_commands()
    assert "./scripts/demo" in found and "./scripts/test" in found       # the quick start
    assert any(c.startswith("edge run") for c in found)                  # a plain fence of edge commands
    text = ("```console\n$ edge listen /dev/x   # the port\nedge | 60 Hz\n```\n```\nA -> B\n```\n```toml\n[x]\n```\n"
            "```bash\n.venv/bin/edge eval --data a \\\n    --json 'out/a b.json'  # two lines\n# a comment\n```\n")
    assert [c for _, c in commands_in(text)] == ["edge listen /dev/x", ".venv/bin/edge eval --data a --json out/a b.json"]


def test_every_command_in_the_docs_is_run_here_or_listed_with_why_not():
    found = doc_commands()
    unlisted = {c: where for c, where in found.items() if c not in RUN and c not in NOT_RUNNABLE}
    assert not unlisted, ("commands in the docs that tests/test_docs.py neither runs (RUN) nor lists as not "
                          "runnable (NOT_RUNNABLE, with the reason):\n" +
                          "\n".join(f"  {where}: {c}" for c, where in unlisted.items()))
    stale = [c for c in [*RUN, *NOT_RUNNABLE] if c not in found]
    assert not stale, "entries in tests/test_docs.py that no doc shows any more:\n  " + "\n  ".join(stale)
    assert not set(RUN) & set(NOT_RUNNABLE)


@pytest.mark.parametrize("command", list(RUN), ids=lambda c: " ".join(c.split()[:4]))
def test_documented_command_runs_and_writes_what_it_names(command, tmp_path):
    where = doc_commands().get(command)
    assert where is not None, f"no doc shows {command!r} any more: drop it from RUN"
    if "../shared/mocap" in command and not (MOCAP / "MANIFEST.tsv").exists():
        pytest.skip(f"needs the training data at {MOCAP} (../shared/mocap)")
    argv, words = runnable(command)
    cwd = checkout_view(tmp_path)
    run = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=180,
                         env={**os.environ, "PYTHONPATH": ""})
    assert run.returncode == 0, (f"{where}: {command}\nran: {shlex.join(argv)}\nexit {run.returncode}\n"
                                 f"{run.stdout[-2000:]}\n{run.stderr[-3000:]}")
    outputs = [(flag, value) for flag, value in zip(words, words[1:], strict=False) if flag in OUTPUT_FLAGS]
    for flag, value in outputs:
        path = cwd / value
        assert path.exists(), f"{where}: {command}\n{flag} {value} was not written"
        if flag == "--report" or (flag == "--out" and words[1] == "report"):
            assert (path / "index.html").is_file(), f"{where}: {command}\nno {value}/index.html"


# A dotted name of one of the project's packages, as the docs cite modules, classes and functions.
DOTTED = re.compile(r"(?<![\w./-])((?:edge|edgetools|firmware_bridge|models|quantize|viz)(?:\.[A-Za-z_]\w*)+)")


def _defined(tree, attrs):
    """Whether the chain `attrs` is defined in a module's syntax tree (a class, function or assignment
    at the top, then inside a class body); None where it passes through an imported name."""
    body = tree.body
    for i, attr in enumerate(attrs):
        found = None
        for node in body:
            if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == attr:
                found = node
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                names = {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
                found = node if attr in names else found
            elif isinstance(node, (ast.Import, ast.ImportFrom)) and \
                    attr in {(a.asname or a.name).split(".")[0] for a in node.names}:
                return None
        if found is None:
            return False
        if i + 1 < len(attrs):
            if not isinstance(found, ast.ClassDef):
                return None         # an attribute of a function or a value: ask the imported module
            body = found.body
    return True


def resolves(name):
    """Whether `name` is a module of the project, or a name defined in one, read from the source, so
    that a module whose optional dependency (torch, matplotlib) is not installed still resolves."""
    import importlib
    import importlib.util
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        try:
            spec = importlib.util.find_spec(".".join(parts[:k]))
        except (ImportError, ValueError):
            spec = None
        if spec is None or not spec.origin or not spec.origin.endswith(".py"):
            continue
        if k == len(parts):
            return True
        defined = _defined(ast.parse(Path(spec.origin).read_text()), parts[k:])
        if defined is not None:
            return defined
        try:                        # through an imported name: import the module to follow it
            obj = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError as e:
            pytest.skip(f"{name} goes through a name {'.'.join(parts[:k])} imports from {e.name}, not installed")
        for attr in parts[k:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_dotted_name_the_docs_cite_exists():
    """README.md and docs/*.md name the code they describe (`edge.ssi.Switcher`, `motion.synth.synthesize`):
    each such name imports, so a rename or a removal shows in the docs that still cite it."""
    cited = {(doc.name, m.group(1).rstrip(".")) for doc in DOCS for m in DOTTED.finditer(doc.read_text())}
    assert len(cited) > 25
    missing = sorted(f"{doc}: {name}" for doc, name in cited if not resolves(name))
    assert not missing, "the docs cite names that do not exist:\n" + "\n".join(missing)


def test_the_readmes_layout_names_every_top_level_package_and_folder_and_no_other():
    """README.md's Layout lists each top-level folder of the repository (`name/`), the Python packages
    in their import-linter layer order (pyproject.toml), and nothing that is not there."""
    import tomllib
    text = (ROOT / "README.md").read_text()
    layout = text[text.index("## Layout"):].split("\n## ", 1)[0]
    listed = re.findall(r"`([a-z_]+)/`", layout)
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    folders = {f.split("/")[0] for f in tracked if "/" in f and not f.startswith(".")}
    assert set(listed) == folders, f"listed but absent: {set(listed) - folders}; absent from Layout: {folders - set(listed)}"
    layers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]["layers"]
    order = [name.strip() for layer in layers for name in layer.split("|")]
    packages = [name for name in listed if (ROOT / name / "__init__.py").exists()]
    assert sorted(packages) == sorted(order)
    assert [p for p in listed if p in order] == order, "the Layout lists the packages out of their layer order"
