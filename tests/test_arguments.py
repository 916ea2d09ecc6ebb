"""Every parq-* command answers nonsense arguments with one line and exit code 2."""
import subprocess
import sys

import pytest

# (module, arguments that are otherwise complete)
COMMANDS = {
    "parq-run": ("parq_runtime.cli", ["frames"]),
    "parq-eval": ("parq_runtime.evaluation", ["pred.json", "boxes.json"]),
    "parq-synth": ("parq_synth.cli", ["out", "--scenes", "1", "--seed", "0"]),
    "parq-export": ("parq_export.cli", ["c.pt"]),
    "parq-train": ("parq_train.cli", ["out.pt"]),
    "python -m parq_train.tune": ("parq_train.tune", ["c.pt", "-o", "o.pt"]),
}


def run(module, *args):
    code = (f"import sys, {module} as m; "
            f"sys.exit(m.main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)


@pytest.mark.parametrize("prog", COMMANDS)
def test_unknown_flag_is_one_line(prog):
    module, args = COMMANDS[prog]
    p = run(module, *args, "--no-such-flag")
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith(f"{prog}: error: ") and "--no-such-flag" in lines[0]
    assert f"see {prog} --help" in lines[0] and "usage:" not in p.stderr


@pytest.mark.parametrize("module,args,needle", [
    ("parq_train.cli", ["out.pt", "--steps", "0"], "--steps: 0 must be at least 1"),
    ("parq_train.cli", ["out.pt", "--lr", "fast"], "'fast' is not a number"),
    ("parq_train.cli", ["out.pt", "--pretrain-steps", "-1"], "-1 must not be negative"),
    ("parq_train.tune", ["c.pt", "-o", "o.pt", "--iters", "0"], "--iters: 0 must be at least 1"),
    ("parq_export.cli", ["c.pt", "--opset", "x"], "'x' is not an integer"),
    ("parq_synth.cli", ["out", "--scenes", "two", "--seed", "0"], "'two' is not an integer"),
])
def test_bad_values_say_what_was_expected(module, args, needle):
    p = run(module, *args)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert needle in p.stderr, p.stderr
