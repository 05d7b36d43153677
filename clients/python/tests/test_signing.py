"""Signed server records (docs/evaluation.md, "Signed records"): the signing rule on a line's bytes,
the key file, and `esrp verify --key`'s checks before any replay — a table of tampered records,
each refused with its reason, against honest ones (one with reward weights), which pass. No server
is started: the checks that refuse need none."""

from __future__ import annotations

import hashlib
import hmac
import json
from pathlib import Path
from typing import Any

import pytest

from esrp.cli import main
from esrp.eval.manifest import MANIFEST, MANIFEST_SCHEMA, ManifestError, load_manifest
from esrp.eval.results import SCHEMA, EpisodeRecord
from esrp.eval.signing import (
    BadSignature,
    RecordsKeyError,
    SigningError,
    UnsignedRecord,
    check,
    load_key,
    require,
    signature_of,
    signed_bytes,
)
from esrp.eval.verify import REFUSED, manifests_beside, read_inputs, refusals

KEY = b"0123456789abcdef0123456789abcdef"
WEIGHTS = {"success": 5.0, "place": 2.0, "unplace": -2.0, "potential": 0.5, "holding": 0.0, "living": -0.01}


def sign(data: dict[str, Any], key: bytes = KEY) -> bytes:
    """The server's line of `data` (docs/evaluation.md): compact JSON, then the HMAC-SHA256 of it
    as its last member, `signature`."""
    body = json.dumps(data, separators=(",", ":"), ensure_ascii=False).encode()
    digest = hmac.new(key, body, hashlib.sha256).hexdigest()
    return body[:-1] + b',"signature":"' + digest.encode() + b'"}'


def record(
    token: str,
    scene: str,
    *,
    success: bool = False,
    horizon: int = 200,
    split: str = "challenge",
    difficulty: str = "easy",
    counted: bool = True,
    weights: dict[str, float] | None = None,
    finished_at: str = "2026-11-23T10:00:00Z",
) -> dict[str, Any]:
    """A server record's members, in the server's order (signature to come)."""
    steps = 40 if success else horizon
    data: dict[str, Any] = {
        "schema": SCHEMA,
        "scene_id": scene,
        "dataset": "esrp-bench-v2",
        "split": split,
        "room_type": "Bedroom",
        "difficulty": difficulty,
        "objects": 1,
        "agent": "mine",
        "agent_config": {},
        "seed": None,
        "success": success,
        "osr": 1.0 if success else 0.5,
        "rdr": 0.0 if success else 0.25,
        "stage": 4 if success else 3,
        "placed": 1 if success else 0,
        "steps": steps,
        "horizon": horizon,
        "end": "success" if success else "horizon",
        "total_reward": 10.5,
        "actions": [0] * steps,
        "wall_seconds": 1.5,
        "agent_stats": {},
        "server_version": "0.2.0",
        "client": "esrp-server 0.2.0",
        "finished_at": finished_at,
        "token": token,
        "started_at": finished_at,
        "dataset_hash": "0123456789abcdef",
        "counted": counted,
    }
    if weights is not None:
        data["reward_weights"] = weights
    data["observations"] = "paper"
    return data


def manifest(folder: Path, horizons: dict[str, int]) -> None:
    scenes = [{"id": s, "difficulty": "easy", "objects": 1, "horizon": h} for s, h in horizons.items()]
    (folder / MANIFEST).write_text(
        json.dumps(
            {
                "schema": MANIFEST_SCHEMA,
                "dataset_hash": "0123456789abcdef",
                "observations": {"challenge": "paper", "minival": "paper"},
                "scenes": scenes,
            }
        )
    )


# ---- the rule on bytes ----------------------------------------------------------------------


def test_the_signed_bytes_are_the_line_less_its_signature_member() -> None:
    # A fixed vector, from `printf %s '{"a":1}' | openssl dgst -sha256 -hmac KEY`.
    digest = "f0546246da9e2349100c845a8561214788d75d900f3c086a72fcfa03bb1f42ab"
    line = b'{"a":1,"signature":"' + digest.encode() + b'"}'
    assert signed_bytes(line) == b'{"a":1}'
    assert signed_bytes(line + b"\n") == b'{"a":1}'
    assert signature_of(line) == digest
    assert check(line, KEY)
    require(line, KEY)
    assert sign({"a": 1}) == line
    assert not check(line, KEY[:-1] + b"X")
    assert not check(line.replace(b"1", b"2", 1), KEY)
    with pytest.raises(BadSignature):
        require(line.replace(b"1", b"2", 1), KEY)
    for unsigned in [
        b'{"a":1}',
        b'{"a":1, "signature": "' + digest.encode() + b'"}',  # not as the server writes it
        b'{"a":1,"signature":"' + digest.upper().encode() + b'"}',  # upper case
        b'{"a":1,"signature":"' + digest[:-1].encode() + b'"}',  # 63 digits
        b'{"signature":"' + digest.encode() + b'","a":1}',  # not last
    ]:
        assert signed_bytes(unsigned) is None, unsigned
        assert not check(unsigned, KEY)
        with pytest.raises(UnsignedRecord):
            require(unsigned, KEY)
    # Both are SigningErrors, and ResultsErrors (the CLI's one-line errors).
    assert issubclass(UnsignedRecord, SigningError)
    assert issubclass(BadSignature, SigningError)


def test_the_key_is_the_files_bytes_with_whitespace_stripped(tmp_path: Path) -> None:
    path = tmp_path / "records.key"
    path.write_bytes(b"  " + KEY + b"\r\n")
    assert load_key(path) == KEY
    path.write_bytes(b"short\n")
    with pytest.raises(RecordsKeyError, match="holds 5 bytes"):
        load_key(path)
    with pytest.raises(RecordsKeyError, match="cannot read the records key"):
        load_key(tmp_path / "missing.key")


def test_a_server_line_reads_and_writes_back_byte_for_byte() -> None:
    line = sign(record("team-a", "challenge/00000", weights=WEIGHTS))
    parsed = EpisodeRecord.from_dict(json.loads(line))
    assert parsed.reward_weights == WEIGHTS
    assert parsed.observations == "paper"
    assert parsed.signature == signature_of(line)
    assert set(parsed.extra) == {"token", "started_at", "dataset_hash", "counted"}
    assert parsed.to_json().encode() == line
    weights = parsed.played_weights()
    assert weights is not None
    assert weights.living == -0.01
    # Other tools' records have none of them, and write none.
    plain = {k: v for k, v in record("a", "s").items() if k not in ("observations",)}
    other = EpisodeRecord.from_dict(plain)
    assert (other.reward_weights, other.observations, other.signature) == (None, None, None)
    assert "observations" not in other.to_json()
    assert other.played_weights() is None
    bad: list[tuple[str, Any]] = [
        ("reward_weights", {"success": 1.0}),
        ("observations", "some"),
        ("signature", 5),
    ]
    for name, value in bad:
        with pytest.raises(ValueError, match=name):
            EpisodeRecord.from_dict(plain | {name: value})


# ---- esrp verify --key: what is refused before any replay -------------------------------------


def honest_lines() -> dict[str, list[bytes]]:
    """Each token's file as the server writes it."""
    return {
        "team-a": [
            sign(record("team-a", "challenge/00000", success=True)),
            sign(record("team-a", "challenge/00001", weights=WEIGHTS, finished_at="2026-11-23T10:05:00Z")),
            sign(record("team-a", "minival/00000", split="minival", counted=False)),
        ],
        "team-b": [sign(record("team-b", "challenge/00000"))],
    }


def write_folder(folder: Path, files: dict[str, list[bytes]]) -> list[Path]:
    folder.mkdir()
    manifest(folder, {"challenge/00000": 200, "challenge/00001": 200, "challenge/00002": 200})
    paths = []
    for name, lines in files.items():
        path = folder / f"{name}.jsonl"
        path.write_bytes(b"".join(line + b"\n" for line in lines))
        paths.append(path)
    return paths


def refused(folder: Path, files: dict[str, list[bytes]]) -> dict[str, list[str]]:
    paths = write_folder(folder, files)
    inputs = read_inputs(paths)
    found = refusals(inputs, KEY, manifests_beside(paths))
    return {inputs[k].where.split("/")[-1]: reasons for k, reasons in found.items()}


def test_honest_records_pass(tmp_path: Path) -> None:
    assert refused(tmp_path / "records", honest_lines()) == {}


def edit(line: bytes, old: bytes, new: bytes) -> bytes:
    assert line.count(old) == 1, old
    return line.replace(old, new)


def rewritten(line: bytes, **more: str) -> bytes:
    data = json.loads(line)
    data.update(more)
    return json.dumps(data, separators=(",", ":")).encode()


def with_member_before_signature(line: bytes) -> bytes:
    return edit(line, b',"signature"', b',"note":"fine","signature"')


HONEST = honest_lines()["team-a"][0]
OTHER_KEY = b"another-key-of-32-bytes-at-least"
TAMPERED: list[tuple[str, dict[str, list[bytes]], str, str]] = [
    # (what, the token files with the tampered one, the file:line refused, its reason)
    ("changed metric", {"team-a": [edit(HONEST, b'"osr":1.0', b'"osr":0.5')]}, "team-a.jsonl:1", "altered"),
    (
        "moved scene",
        {"team-a": [edit(HONEST, b"challenge/00000", b"challenge/00002")]},
        "team-a.jsonl:1",
        "altered",
    ),
    ("flipped split", {"team-a": [edit(HONEST, b'"challenge"', b'"minival"')]}, "team-a.jsonl:1", "altered"),
    (
        "flipped counted",
        {"team-a": [edit(HONEST, b'"counted":true', b'"counted":false')]},
        "team-a.jsonl:1",
        "altered",
    ),
    (
        "longer horizon",
        {"team-a": [edit(HONEST, b'"horizon":200', b'"horizon":400')]},
        "team-a.jsonl:1",
        "altered",
    ),
    (
        "another token's name",
        {"team-b": [edit(HONEST, b'"token":"team-a"', b'"token":"team-b"')]},
        "team-b.jsonl:1",
        "altered",
    ),
    ("a member added", {"team-a": [with_member_before_signature(HONEST)]}, "team-a.jsonl:1", "altered"),
    (
        "signed with another key",
        {"team-a": [sign(record("team-a", "challenge/00000"), OTHER_KEY)]},
        "team-a.jsonl:1",
        "altered",
    ),
    (
        "re-serialised with a new field",
        {"team-a": [rewritten(HONEST, note="fine")]},
        "team-a.jsonl:1",
        "unsigned: its signature is not the last member",
    ),
    (
        "re-serialised as is",
        {"team-a": [json.dumps(json.loads(HONEST)).encode()]},
        "team-a.jsonl:1",
        "unsigned: its signature is not the last member",
    ),
    (
        "unsigned",
        {"team-a": [json.dumps(record("team-a", "challenge/00000"), separators=(",", ":")).encode()]},
        "team-a.jsonl:1",
        "unsigned: no signature member",
    ),
    (
        "moved token file",
        {"team-a": honest_lines()["team-a"][1:], "team-b": [HONEST]},
        "team-b.jsonl:1",
        "moved: a record of token 'team-a' in team-b.jsonl",
    ),
    ("duplicate", {"team-a": [HONEST, HONEST]}, "team-a.jsonl:2", "duplicate: the same signature as "),
    # Signed, so by the server or whoever holds its key, and still not what the server writes:
    (
        "a second counted record",
        {"team-a": [HONEST, sign(record("team-a", "challenge/00000", finished_at="2026-11-23T11:00:00Z"))]},
        "team-a.jsonl:2",
        "duplicate: a second counted record of 'team-a' on challenge/00000",
    ),
    (
        "signed with a longer horizon",
        {"team-a": [sign(record("team-a", "challenge/00000", horizon=400))]},
        "team-a.jsonl:1",
        "horizon: recorded 400, the scene's is 200",
    ),
    (
        "signed with another split",
        {"team-a": [sign(record("team-a", "challenge/00000", split="minival"))]},
        "team-a.jsonl:1",
        "split: recorded 'minival', the scene's is 'challenge'",
    ),
    (
        "signed with another difficulty",
        {"team-a": [sign(record("team-a", "challenge/00000", difficulty="hard"))]},
        "team-a.jsonl:1",
        "difficulty: recorded 'hard', the scene's is 'easy'",
    ),
    (
        "a scene not in the challenge",
        {"team-a": [sign(record("team-a", "challenge/00099"))]},
        "team-a.jsonl:1",
        "scene: 'challenge/00099' is not one of the challenge's scenes",
    ),
]


@pytest.mark.parametrize(("what", "files", "where", "reason"), TAMPERED, ids=[t[0] for t in TAMPERED])
def test_a_tampered_record_is_refused_with_its_reason(
    tmp_path: Path, what: str, files: dict[str, list[bytes]], where: str, reason: str
) -> None:
    # The tampered file beside the other token's honest file (or team-a's, for team-b's).
    honest = honest_lines()
    others = {name: lines for name, lines in honest.items() if name not in files}
    found = refused(tmp_path / "records", others | files)
    assert list(found) == [where], (what, found)
    (text,) = found[where]
    assert text.startswith(REFUSED + reason), (what, text)


def test_verify_says_when_the_key_cannot_be_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (path,) = write_folder(tmp_path / "records", {"team-a": honest_lines()["team-a"]})
    code = main(["verify", str(path), "--key", str(tmp_path / "nope.key"), "--server", "127.0.0.1:9"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("esrp verify: cannot read the records key"), err
    assert err.count("\n") == 1


def test_a_bad_scene_list_is_named(tmp_path: Path) -> None:
    path = tmp_path / MANIFEST
    path.write_text(
        '{"schema": "esrp.challenge-scenes/v1", "dataset_hash": "x", "observations": {}, '
        '"scenes": [{"id": "challenge/00000", "difficulty": "trivial", "objects": 1, "horizon": 1}]}'
    )
    with pytest.raises(ManifestError, match=r"scenes\[0\]"):
        load_manifest(path)
