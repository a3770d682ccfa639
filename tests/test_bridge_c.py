"""The C reference implementation against the Python one: shared vectors both ways, fuzz, no dynamic memory."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from firmware_bridge.cobs import cobs_encode
from firmware_bridge.testing import (
    FIRMWARE_DIR,
    VECTORS_PATH,
    build_harness,
    c_compiler,
    decode_lines,
    expected_segments,
    fuzz_stream,
    read_vectors,
    run_harness,
    vector_lines,
)

pytestmark = pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # -Werror -pedantic, with AddressSanitizer and UBSan: an out-of-bounds access aborts the run
    return build_harness(tmp_path_factory.mktemp("c"), sanitize=True)


def test_vectors_file_is_current() -> None:
    """The checked-in vectors are what the Python encoder produces: the bytes of v1 cannot drift silently."""
    assert VECTORS_PATH.read_text().splitlines() == vector_lines()


def test_c_decodes_every_vector_as_stated(harness: Path) -> None:
    vectors = read_vectors()
    out = run_harness(harness, "decode", b"".join(wire for _, wire in vectors)).splitlines()
    assert out[:-1] == [text for text, _ in vectors]
    n_ok = sum(not t.startswith("REJECT") for t, _ in vectors)
    assert out[-1].startswith(f"STATS ok={n_ok} ")


def test_python_decodes_every_vector_as_stated() -> None:
    vectors = read_vectors()
    lines = decode_lines(b"".join(wire for _, wire in vectors))
    assert lines[:-1] == [text for text, _ in vectors]


def test_c_encodes_every_vector_to_the_same_bytes(harness: Path) -> None:
    messages = [(text, wire) for text, wire in read_vectors() if not text.startswith("REJECT")]
    out = run_harness(harness, "encode", "".join(text + "\n" for text, _ in messages).encode()).split()
    assert [bytes.fromhex(h) for h in out] == [wire for _, wire in messages]


def test_c_and_python_agree_frame_by_frame_on_a_fuzzed_stream(harness: Path) -> None:
    stream, originals = fuzz_stream(20_000, seed=7)
    c_lines = run_harness(harness, "decode", stream).splitlines()
    py_lines = decode_lines(stream)
    assert c_lines == py_lines  # same accepted frames, same rejects with the same reasons, same order
    accepted = [line for line in py_lines if not line.startswith(("REJECT", "STATS"))]
    assert len(accepted) == len(expected_segments(stream, originals))


def test_c_digest_mode_matches_decode_mode(harness: Path) -> None:
    stream, _ = fuzz_stream(2_000, seed=8)
    digest = run_harness(harness, "digest", stream).splitlines()
    assert digest[1] == run_harness(harness, "decode", stream).splitlines()[-1]
    assert re.fullmatch(r"DIGEST [0-9a-f]{8}", digest[0])


def test_protocol_md_examples_are_vectors() -> None:
    text = (FIRMWARE_DIR.parent / "PROTOCOL.md").read_text()
    bodies = re.findall(r"^body: ([0-9a-f ]+)$", text, re.M)
    wires = re.findall(r"^wire: ([0-9a-f ]+)$", text, re.M)
    assert len(bodies) == len(wires) == 4
    vector_wires = {wire for _, wire in read_vectors()}
    for body, wire in zip(bodies, wires):
        assert cobs_encode(bytes.fromhex(body)) + b"\x00" == bytes.fromhex(wire)
        assert bytes.fromhex(wire) in vector_wires


def test_library_uses_no_heap_and_no_libc(tmp_path: Path) -> None:
    obj = tmp_path / "acesplat_bridge.o"
    cc = c_compiler()
    flags = ["-std=c99", "-pedantic", "-Wall", "-Wextra", "-Wconversion", "-Wshadow", "-Werror", "-O2", "-c"]
    subprocess.run([cc, *flags, str(FIRMWARE_DIR / "acesplat_bridge.c"), "-o", str(obj)], check=True)
    undefined = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True, check=True).stdout.split()
    assert not [s for s in undefined if s not in ("U", "memcpy", "memset")], undefined
    assert not re.search(r"\b(malloc|calloc|realloc|free)\s*\(", (FIRMWARE_DIR / "acesplat_bridge.c").read_text())
