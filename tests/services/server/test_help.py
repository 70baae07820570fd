"""`fracto-server --help` tells an operator every flag's meaning, environment variable and default."""

import subprocess
import sys
from pathlib import Path

from fractoscope.server.config import build_parser


def test_every_flag_says_what_it_is_and_its_default():
    for action in build_parser()._actions:
        if action.dest == "help":
            continue
        assert action.help and "default" in action.help, action.option_strings
    shown = subprocess.run(
        [str(Path(sys.executable).with_name("fracto-server")), "--help"], capture_output=True, text=True, timeout=60
    )
    assert shown.returncode == 0 and "FRACTO_ADDRESS; default [::]:50051" in " ".join(shown.stdout.split())
    assert "FRACTO_HTTP_ADDRESS; default 0.0.0.0:8080" in " ".join(shown.stdout.split())
