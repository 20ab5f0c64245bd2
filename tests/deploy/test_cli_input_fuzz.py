"""Careless input on the `impulse` command line never ends in a traceback.

Random and damaged config files, odd `key=value` overrides and paths of the wrong kind are given to the CLI's
`main` in-process, with `--print-config` so that nothing but argument parsing and config loading runs (no JAX):
each must end with exit status 2 and a short message on stderr, or (for input that happens to be valid) status 0
with the config printed. A few real processes check what only a process shows: /dev/zero as a config file ends at
once, a pipe closed early (`| head`) ends quietly, and a run name that cannot be a folder name fails before anything
slow starts. Seeded, so a failure names a case that can be replayed.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from impulse.deploy.cli import main
from impulse.deploy.commands import config as config_command
from impulse.deploy.config import (
    MAX_CONFIG_BYTES,
    MAX_OVERRIDE_BYTES,
    ConfigError,
    read_config_bytes,
    resolve_config,
)
from impulse.deploy.config_reference import keys
from impulse.deploy.run_config import MAX_RUN_NAME, RunConfig, check_run_name
from impulse.deploy.runtime.exit_codes import EXIT_BROKEN_PIPE
from tests.support.paths import REPO

SEED = 53
USAGE = 2
MAX_LINES = 8
"""argparse's own errors print the command's usage (a few lines) above the one-line error."""

KEYS = [k.name for k in keys()]
QUICK = REPO / "configs" / "quick-cpu.toml"
TOML_VALUES = ['"text"', "1", "-7", "0", "1.5", "nan", "inf", "-inf", "true", "false", "[]", "[1, 2]", '["a", 1]',
               "{a = 1}", "1979-05-27", "07:32:00", '"\\u0000"', '"a/b"', '"none"', "9" * 5000, "[" * 50 + "]" * 50,
               '"' + "x" * 5000 + '"', "1e400", '"dr"', '"random"', '""']


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of `main(argv)`, whether it returns its status or argparse exits."""
    try:
        code = main(argv)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else 1
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_refused(result: tuple[int, str, str], case: object, one_line: bool = True) -> str:
    code, out, err = result
    assert code == USAGE, (case, code, err[-2000:])
    assert "Traceback" not in err, (case, err[-2000:])
    lines = err.strip().splitlines()
    assert lines and len(lines) <= (1 if one_line else MAX_LINES), (case, err[-2000:])
    assert len(err) < 5000, (case, len(err))
    return err


def assert_refused_or_valid(result: tuple[int, str, str], case: object) -> bool:
    """Valid input prints the config (status 0); anything else is refused in one line. Whether it was refused."""
    code, out, err = result
    if code == 0:
        tomllib.loads(out)  # --print-config printed a config that reads back
        return False
    assert_refused(result, case)
    return True


# ---- config files ----------------------------------------------------------------------------------------------


def random_config_bytes(rng: random.Random, case: int, valid: bytes, huge: bool = True) -> bytes:
    """One damaged or random config file; the kind cycles with `case` so that each kind is covered. `huge`: files of
    about the size limit among them (slow to write: megabytes each)."""
    kind = case % 8
    if kind == 3 and not huge:
        kind = 4
    if kind == 0:  # random bytes, invalid UTF-8 most of the time
        return rng.randbytes(rng.randrange(1, 2000))
    if kind == 1:  # a valid file with a few bytes changed
        data = bytearray(valid)
        for _ in range(rng.randrange(1, 6)):
            data[rng.randrange(len(data))] = rng.randrange(256)
        return bytes(data)
    if kind == 2:  # NUL bytes among the text
        data = bytearray(valid)
        for _ in range(rng.randrange(1, 4)):
            data.insert(rng.randrange(len(data)), 0)
        return bytes(data)
    if kind == 3:  # a huge line: some over the size limit, some under it
        size = rng.choice([200_000, MAX_CONFIG_BYTES - 100, MAX_CONFIG_BYTES + 1, 3 * MAX_CONFIG_BYTES])
        return rng.choice([b"# ", b"seed = ", b'name = "', b"x = '"]) + b"a" * size
    if kind == 4:  # valid TOML, values of the wrong (or right) type
        lines = [f"{rng.choice(KEYS)} = {rng.choice(TOML_VALUES)}" for _ in range(rng.randrange(1, 4))]
        return "\n".join(lines).encode()
    if kind == 5:  # a table where a value is expected, or a value where a table is
        section = rng.choice(KEYS).split(".")[0]
        return rng.choice([f"{section} = 3\n", f"[{section}]\n[{section}]\n", f"[[{section}]]\nx = 1\n",
                           f"[{rng.choice(KEYS)}]\nx = 1\n"]).encode()
    if kind == 6:  # valid text cut at a random place, or a random line of valid text repeated
        cut = valid[:rng.randrange(len(valid))]
        return cut if rng.random() < 0.5 else b"\n".join([rng.choice(valid.splitlines())] * 3)
    return rng.choice([b"\xef\xbb\xbfseed = 1\n", b"seed = 1\r\nseed = 2\n",
                       b"\xff\xfe" + "seed = 1".encode("utf-16le"), "name = \"caf\u00e9\"\n".encode(),
                       b'name = "a/b"\n', b'name = ".hidden"\n',
                       b"[ppo]\nlearning_rate = nan\n", "ppo.num_envs = '\U0001f600'\n".encode()])


def test_random_config_files_are_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Through `main`: each file is either a valid config (printed) or refused with one line, status 2."""
    rng = random.Random(SEED)
    valid = QUICK.read_bytes()
    path = tmp_path / "fuzz.toml"
    refused = 0
    for case in range(64):
        path.write_bytes(random_config_bytes(rng, case, valid))
        refused += assert_refused_or_valid(run_cli(["train", "--config", str(path), "--print-config"], capsys),
                                           (case, path.read_bytes()[:200]))
    assert refused > 48, refused


def test_many_more_config_files_raise_only_config_errors(tmp_path: Path) -> None:
    """The same kinds of files, many more of them, through the loader alone (what `main` turns into one line)."""
    rng = random.Random(SEED + 1)
    valid = QUICK.read_bytes()
    path = tmp_path / "fuzz.toml"
    for case in range(400):
        path.write_bytes(random_config_bytes(rng, case, valid, huge=False))
        try:
            resolve_config(RunConfig, path, [])
        except ConfigError as err:
            message = str(err)
            assert message.isprintable() and len(message) < 5000, (case, message[:300])


def test_config_file_errors_name_the_file_and_the_place(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'seed = 1\nname = "caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"bad\.toml is not UTF-8 text: byte 0xe9 at offset 20 \(line 2\)"):
        resolve_config(RunConfig, bad, [])
    bad.write_text("seed = 1\n[ppo]\nnum_envs = = 4\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: invalid TOML: .*line 3, column 12"):
        resolve_config(RunConfig, bad, [])
    bad.write_text("seed = " + "[" * 100_000)
    with pytest.raises(ConfigError, match="nested too deeply"):
        resolve_config(RunConfig, bad, [])
    bad.write_text("seed = " + "9" * 5000)
    with pytest.raises(ConfigError, match=r"bad\.toml: invalid TOML"):
        resolve_config(RunConfig, bad, [])
    bad.write_text('run_dir = "runs/\\u0000"\n')
    with pytest.raises(ConfigError, match="config key 'run_dir' holds a NUL character"):
        resolve_config(RunConfig, bad, [])


def test_a_file_larger_than_its_size_says_is_cut_at_the_limit() -> None:
    """The second guard behind the regular-file check: /proc files are regular files whose size reads 0."""
    status = Path("/proc/self/status")
    if not status.is_file():
        pytest.skip("no /proc")
    with pytest.raises(ConfigError, match="larger than 16 bytes"):
        read_config_bytes(status, limit=16)


# ---- overrides -------------------------------------------------------------------------------------------------


ODD_OVERRIDES = [
    "ppo.num_envs=abc", "ppo.learning_rate=nan", "ppo.learning_rate=-nan", "=x", "=", "x=", ".=1", "ppo.=1",
    "ppo..num_envs=1", " =1", "ppö.num_envs=1", "ключ=1", "ppo.num_envs=\U0001f600", "name=a/b", "name=..",
    "name=.hidden", "name=-x", "name=a b", "name=a*", "name=", "name=caf\u00e9", "name=" + "a" * (MAX_RUN_NAME + 1),
    "name=" + "a" * (MAX_OVERRIDE_BYTES + 1), "ppo.num_envs=" + "9" * 5000, "ppo.learning_rate=" + "9" * 4000,
    "seed=" + "[" * 10_000, "seed={a = 1}", "seed=1979-05-27", "seed=true", "seed=1.5", "ppo=3", "ppo.num_envs.x=1",
    "curriculum=nosuch", "env.size=xl", "run_dir=a\x00b", "name=a\x00", "a\x00=1", "name=\udcff", "na\udcffme=x",
    "name=\ud800", "seed=1\n2", "a\nb=1", "x" * 70_000 + "=1", "run_dir=" + "d" * 60_000 + "\x00",
]


def test_odd_overrides_are_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    for override in ODD_OVERRIDES:
        assert_refused(run_cli(["train", override, "--print-config"], capsys), override[:80])


def test_unknown_keys_still_suggest_the_close_ones(capsys: pytest.CaptureFixture[str]) -> None:
    err = assert_refused(run_cli(["train", "ppo.learnin_rate=1", "--print-config"], capsys), "suggestion")
    assert "did you mean 'ppo.learning_rate'?" in err
    err = assert_refused(run_cli(["train", "ppo.num-envs=1\n", "--print-config"], capsys), "suggestion")
    assert "did you mean 'ppo.num_envs'?" in err


def test_random_overrides_are_valid_or_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    rng = random.Random(SEED + 2)
    alphabet = "abc.=_-/ \t\n\x00\x7f\u00e9\U0001f600[]{}\"'#,0123456789eE+\udcff"
    for case in range(40):
        key = rng.choice(KEYS) if rng.random() < 0.7 else "".join(rng.choices(alphabet, k=rng.randrange(8)))
        value = rng.choice(TOML_VALUES) if rng.random() < 0.5 else "".join(rng.choices(alphabet, k=rng.randrange(20)))
        assert_refused_or_valid(run_cli(["train", f"{key}={value}", "--print-config"], capsys), (case, key, value))


def test_run_names() -> None:
    for good in ("default", "quick-cpu", "general-s-gpu-kinetix", "a.b_c-1", "_x", "7", "a" * MAX_RUN_NAME):
        assert check_run_name(good) == good
    for bad, why in (("a/b", "may hold ASCII letters, digits, '.', '_' and '-' only"), ("..", "may not start with '.'"),
                     (".x", "may not start with '.'"), ("-x", "may not start with '-'"), ("a b", "only"), ("é", "only"),
                     ("a\\b", "only"), ("", "empty"), ("a" * (MAX_RUN_NAME + 1), "characters long")):
        with pytest.raises(ValueError, match=why):
            check_run_name(bad)
    with pytest.raises(ValueError, match="name: 'a/b' may hold"):
        RunConfig(name="a/b")


# ---- paths -----------------------------------------------------------------------------------------------------


def odd_paths(tmp_path: Path) -> dict[str, str]:
    """Paths of every wrong kind, by what they are."""
    a_file = tmp_path / "file.toml"
    a_file.write_text("seed = 1\n")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    return {"file": str(a_file), "directory": str(tmp_path), "fifo": str(fifo), "device": "/dev/zero",
            "missing": str(tmp_path / "missing"), "nul": str(tmp_path / "a\x00b"), "long": "a" * 5000,
            "under a file": str(a_file / "x"), "symlink loop": str(loop), "empty": ""}


def test_config_paths_of_the_wrong_kind_are_refused_in_one_line(tmp_path: Path, capsys) -> None:
    paths = odd_paths(tmp_path)
    big = tmp_path / "big.toml"
    with big.open("wb") as f:
        f.truncate(MAX_CONFIG_BYTES + 1)
    paths["too big"] = str(big)
    for kind, path in paths.items():
        if kind == "file":
            continue
        started = time.monotonic()
        err = assert_refused(run_cli(["train", "--config", path, "--print-config"], capsys), kind)
        assert time.monotonic() - started < 5, kind
        assert "config error" in err, (kind, err)


def test_directory_options_of_the_wrong_kind_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--resume, --run, --init-from and --checkpoint name directories: anything else is refused at parsing (a
    missing one is the command's to explain, as it knows what it looked for)."""
    paths = odd_paths(tmp_path)
    commands = [["train", "--resume"], ["train", "--init-from"], ["launch", "--resume"], ["learner", "--run"],
                ["actor", "--run"], ["eval", "--checkpoint"], ["export", "--out", str(tmp_path / "o"), "--checkpoint"],
                ["curriculum", "get", "--run"], ["studio", "--run"]]
    kinds = ["file", "fifo", "device", "nul", "long", "under a file", "symlink loop", "empty"]
    cases = [(kind, commands[0]) for kind in kinds]  # every kind for one option, every option for some kinds
    cases += [(kinds[(i * 3 + j) % len(kinds)], command) for i, command in enumerate(commands[1:]) for j in range(3)]
    for kind, command in cases:
        option = command[-1]
        err = assert_refused(run_cli([*command, paths[kind], "--print-config"], capsys), (kind, command),
                             one_line=False)
        assert f"error: argument {option}:" in err.splitlines()[-1], (kind, command, err)


def test_an_unexpected_error_while_reading_the_config_is_one_line(monkeypatch, capsys) -> None:
    """The general guard: a bug in the reading code is reported, not turned into a traceback."""
    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("reader bug\nsecond line")

    monkeypatch.setattr("impulse.deploy.cli.resolve_config", broken)
    err = assert_refused(run_cli(["train", "--print-config"], capsys), "guard")
    assert "RuntimeError: reader bug\\nsecond line" in err


def test_a_broken_pipe_that_is_not_stdout_is_not_hidden(monkeypatch, capsys) -> None:
    def broken(*args: object, **kwargs: object) -> str:
        raise BrokenPipeError("a socket")

    monkeypatch.setattr(config_command, "as_text", broken)  # where `impulse config describe` calls it
    with pytest.raises(BrokenPipeError):
        main(["config", "describe", "ppo"])


# ---- real processes --------------------------------------------------------------------------------------------


def child_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}


def impulse(*args: str, **kwargs: object) -> subprocess.Popen[bytes]:
    """`python -m impulse.deploy.cli ARGS` as a child process."""
    return subprocess.Popen([sys.executable, "-m", "impulse.deploy.cli", *args], cwd=REPO, env=child_env(), **kwargs)


def test_dev_zero_as_config_ends_at_once() -> None:
    started = time.monotonic()
    proc = impulse("train", "--config", "/dev/zero", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == USAGE, err
    assert err.decode().strip() == ("impulse train: config error: config file /dev/zero is not a regular file (a "
                                    "device, pipe or socket): give a TOML file")
    assert time.monotonic() - started < 10


def test_a_run_name_with_a_slash_fails_before_anything_slow() -> None:
    started = time.monotonic()
    proc = impulse("train", "name=a/b", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == USAGE, err
    assert err.decode().strip().endswith("name: 'a/b' may hold ASCII letters, digits, '.', '_' and '-' only"), err
    assert time.monotonic() - started < 10


def test_output_cut_short_by_head_ends_quietly() -> None:
    """`impulse config describe curriculum | head -1`, in a shell, and with the pipe closed before anything is
    written (so the write fails for certain): no traceback, and status 141 when the write failed."""
    line = f"set -o pipefail; '{sys.executable}' -m impulse.deploy.cli config describe curriculum | head -1"
    shell = subprocess.run(["bash", "-c", line], cwd=REPO, capture_output=True, text=True, timeout=60, env=child_env())
    assert shell.stdout.startswith("curriculum."), shell
    assert shell.returncode in (0, EXIT_BROKEN_PIPE) and "Traceback" not in shell.stderr, shell.stderr

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = impulse("config", "describe", stdout=write_end, stderr=subprocess.PIPE)
    finally:
        os.close(write_end)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_BROKEN_PIPE, err
    assert err == b"", err
