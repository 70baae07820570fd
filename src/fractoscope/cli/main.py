"""`fracto`: the command line of Fractoscope; each verb group lives in its own module.

Exit codes: 0 success, 1 unexpected failure, 2 bad input, 3 server unavailable, 4 not found.
"""

from __future__ import annotations

import argparse
import sys

import grpc

from fractoscope.cli import demo, export, height, mesh, specimen
from fractoscope.cli.common import (
    EXIT_BAD_INPUT, EXIT_CODES, EXIT_FAILURE, SuggestingParser, UsageError, in_command_line_terms, is_connection_failure, reject_unknown,
    unavailable_sentence,
)
from fractoscope.client import ClientError
from fractoscope.errors import InvalidInputError


def build_parser() -> argparse.ArgumentParser:
    parser = SuggestingParser(prog="fracto", description="Calibrated 3D fracture surfaces from SEM stereo pairs.")
    commands = parser.add_subparsers(dest="command", required=True)
    for verbs in (height, mesh, specimen, export, demo):
        verbs.add_parsers(commands)
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args, extras = parser.parse_known_args(argv)
    reject_unknown(parser, args, extras)
    try:
        code = args.run(args)
    except UsageError as error:
        print(f"error: {error}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    except InvalidInputError as error:
        print(f"error: {in_command_line_terms(error.field, str(error), args)}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    except ClientError as error:
        if error.code == grpc.StatusCode.UNAVAILABLE and is_connection_failure(str(error)):
            message = unavailable_sentence(getattr(args, "server", None))
        else:
            message = in_command_line_terms(error.field, str(error), args)
        print(f"error: {message}", file=sys.stderr)
        code = EXIT_CODES.get(error.code, EXIT_FAILURE)
    except (OSError, RuntimeError) as error:  # e.g. a port in use: one line, not a traceback
        print(f"error: {error}", file=sys.stderr)
        code = EXIT_FAILURE
    except KeyboardInterrupt:
        code = 130
    sys.exit(code)
