"""`fracto`: the command line of Fractoscope; each verb group lives in its own module, which
imports the numeric stack only when a verb runs.

Exit codes, from the one status table (errors.OUTCOMES): 0 success, 1 unexpected failure, 2 bad
input, 3 server unavailable or busy, 4 not found, 5 not authorized, 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys

from fractoscope.cli import demo, export, height, instrument, mesh, specimen
from fractoscope.cli.common import (
    SuggestingParser,
    UsageError,
    in_command_line_terms,
    is_connection_failure,
    reject_unknown,
    unavailable_sentence,
)
from fractoscope.errors import OUTCOMES, FractoscopeError, outcome_of, outcome_of_code
from fractoscope.rpc.status import ClientError

EXIT_BAD_INPUT = OUTCOMES["INVALID_ARGUMENT"].exit_code
EXIT_FAILURE = OUTCOMES["INTERNAL"].exit_code
# The distributions a verb that works on this machine needs beyond the client.
LOCAL_EXTRA = "pip install 'fractoscope-cli[local]'"


def build_parser() -> argparse.ArgumentParser:
    parser = SuggestingParser(prog="fracto", description="Calibrated 3D fracture surfaces from SEM stereo pairs.")
    commands = parser.add_subparsers(dest="command", required=True)
    for verbs in (height, mesh, specimen, export, instrument, demo):
        verbs.add_parsers(commands)
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args, extras = parser.parse_known_args(argv)
    reject_unknown(parser, args, extras)
    try:
        code = args.run(args)
    except UsageError as error:
        code = _failed(str(error), EXIT_BAD_INPUT)
    except FractoscopeError as error:
        code = _failed(
            in_command_line_terms(getattr(error, "field", None), str(error), args), outcome_of(error).exit_code
        )
    except ClientError as error:
        if error.code.name == "UNAVAILABLE" and is_connection_failure(str(error)):
            message = unavailable_sentence(getattr(args, "server", None), str(error))
        else:
            message = in_command_line_terms(error.field, str(error), args)
        code = _failed(message, outcome_of_code(error.code.name).exit_code)
    except ModuleNotFoundError as error:
        if not (error.name or "").startswith("fractoscope."):
            raise
        code = _failed(
            f"fracto {args.command} works on this machine and needs the services installed: {LOCAL_EXTRA}",
            EXIT_BAD_INPUT,
        )
    except (OSError, RuntimeError) as error:  # e.g. a port in use: one line, not a traceback
        code = _failed(str(error), EXIT_FAILURE)
    except KeyboardInterrupt:
        code = OUTCOMES["CANCELLED"].exit_code
    sys.exit(code)


def _failed(message: str, code: int) -> int:
    print(f"error: {message}", file=sys.stderr)
    return code
