"""The checked-in esrp.v1 stubs are what the pinned grpcio-tools and mypy-protobuf make of proto/."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TOOL = Path(__file__).resolve().parents[1] / "tools" / "generate_proto.py"


def load_tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("generate_proto", TOOL)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["generate_proto"] = module
    spec.loader.exec_module(module)
    return module


def test_checked_in_stubs_are_fresh(tmp_path: Path) -> None:
    tool = load_tool()
    generated = tool.generate(tmp_path)
    assert sorted(generated) == sorted(tool.GENERATED)
    stale = tool.stale_files(generated)
    assert not stale, "stale stubs: run python clients/python/tools/generate_proto.py\n" + "\n".join(
        diff[:2000] for diff in stale.values()
    )


def test_staleness_is_detected(tmp_path: Path) -> None:
    """The comparison itself works: a copy with one changed line is reported."""
    tool = load_tool()
    generated = tool.generate(tmp_path / "generated")
    copy = tmp_path / "copy"
    copy.mkdir()
    for name, text in generated.items():
        (copy / name).write_text(text)
    assert tool.stale_files(generated, copy) == {}
    (copy / "esrp_pb2.py").write_text(generated["esrp_pb2.py"] + "# edited by hand\n")
    assert list(tool.stale_files(generated, copy)) == ["esrp_pb2.py"]


def test_installed_stubs_match_the_source() -> None:
    """The installed package carries the checked-in stubs (the wheel is built from them)."""
    import esrp.v1.esrp_pb2 as installed

    source = TOOL.parents[1] / "src" / "esrp" / "v1" / "esrp_pb2.py"
    assert Path(installed.__file__).read_text() == source.read_text()
    assert installed.DESCRIPTOR.name == "esrp/v1/esrp.proto"
