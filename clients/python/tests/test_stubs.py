"""The checked-in esrp.v1 stubs are what the pinned grpcio-tools and mypy-protobuf make of proto/."""

from __future__ import annotations

from pathlib import Path

from conftest import load_tool, needs


def test_checked_in_stubs_are_fresh(tmp_path: Path) -> None:
    needs("grpc_tools", "stubs")
    tool = load_tool("generate_proto")
    generated = tool.generate(tmp_path)
    assert sorted(generated) == sorted(tool.GENERATED)
    stale = tool.stale_files(generated)
    assert not stale, "stale stubs: run python clients/python/tools/generate_proto.py\n" + "\n".join(
        diff[:2000] for diff in stale.values()
    )


def test_staleness_is_detected(tmp_path: Path) -> None:
    """The comparison itself works: a copy with one changed line is reported."""
    needs("grpc_tools", "stubs")
    tool = load_tool("generate_proto")
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

    source = Path(__file__).resolve().parents[1] / "src" / "esrp" / "v1" / "esrp_pb2.py"
    assert Path(installed.__file__).read_text() == source.read_text()
    assert installed.DESCRIPTOR.name == "esrp/v1/esrp.proto"
