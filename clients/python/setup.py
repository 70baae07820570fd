"""Generates the gRPC stubs of ../../proto/fractoscope/v1 into fractoscope/v1 before setuptools
looks for packages, so that every build (wheel or editable) carries stubs of the proto it sits
beside. A source tree without the proto folder (an sdist) keeps the stubs it was built with."""

from pathlib import Path

from setuptools import setup

HERE = Path(__file__).resolve().parent
PROTO_ROOT = HERE.parents[1] / "proto"
STUBS = HERE / "fractoscope" / "v1"


def generate_stubs() -> None:
    from grpc_tools import protoc

    protos = sorted(str(path) for path in (PROTO_ROOT / "fractoscope" / "v1").glob("*.proto"))
    STUBS.mkdir(parents=True, exist_ok=True)
    include = str(Path(protoc.__file__).parent / "_proto")
    arguments = [
        "protoc",
        f"-I{PROTO_ROOT}",
        f"-I{include}",
        f"--python_out={HERE}",
        f"--pyi_out={HERE}",
        f"--grpc_python_out={HERE}",
    ]
    if protoc.main([*arguments, *protos]) != 0:
        raise SystemExit(f"protoc failed on {PROTO_ROOT}")
    (STUBS / "__init__.py").write_text(
        '"""Generated from proto/fractoscope/v1 by clients/python/setup.py; never edited."""\n'
    )


if PROTO_ROOT.is_dir():
    generate_stubs()
setup()
