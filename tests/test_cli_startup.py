"""`cvqpg --version` and every `--help` answer from the parser alone: no PyTorch, Numba, Pillow or Ray imported."""

import json
import subprocess
import sys

from cvqpg.cli import build_parser

HEAVY = ("torch", "numba", "PIL", "ray", "cvqpg.fitting", "cvqpg.campaign.bench", "cvqpg.app.compilation",
         "cvqpg.app.executors")
# In a fresh interpreter: run the command line's --version and each subcommand's --help, then list what they imported.
PROBE = """
import contextlib, io, json, sys
from cvqpg.cli import main
for args in json.loads(sys.argv[1]):
    with contextlib.redirect_stdout(io.StringIO()) as shown:
        assert main(args) == 0, args
    assert shown.getvalue(), args
print(json.dumps(sorted(name for name in json.loads(sys.argv[2]) if name in sys.modules)))
"""


def subcommands() -> list[str]:
    actions = build_parser()._subparsers._group_actions
    return sorted(name for action in actions for name in action.choices)


def test_version_and_every_help_import_no_heavy_module():
    commands = [["--version"], ["--help"], *([name, "--help"] for name in subcommands())]
    assert ["fit", "--help"] in commands and ["compile", "--help"] in commands
    done = subprocess.run([sys.executable, "-c", PROBE, json.dumps(commands), json.dumps(HEAVY)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []



def test_every_help_shows_each_default_once_in_one_style():
    parser = build_parser()
    for name, sub in parser._subparsers._group_actions[0].choices.items():
        assert "(default" not in sub.format_help(), name
        formatter = sub._get_formatter()
        for action in sub._actions:
            text = formatter._get_help_string(action)
            assert text.count("[default") <= 1, (name, action.dest)
            if isinstance(action.default, (int, float)) and not isinstance(action.default, bool):
                assert "[default" in text, (name, action.dest)  # 0 too, which compares equal to False
