"""The --http-tokens file: its format, what it refuses (by file and line), lookups, reloads and `gmmap token`."""

from __future__ import annotations

import hashlib
import stat

import pytest

from services import cli
from services.map_server import tokens
from services.map_server.tokens import Client, TokenFile, new_token, parse_tokens, read_tokens


def test_a_new_token_is_256_random_bits_and_only_its_hash_is_written():
    token, client = new_token("ops")
    again, _ = new_token("ops")
    assert token.startswith("gmmap_") and token != again
    assert len(token) == len("gmmap_") + 43  # 32 bytes, base64url without padding
    assert client.digest == hashlib.sha256(token.encode()).digest()
    assert token not in client.line() and client.line() == f"ops sha256:{client.digest.hex()}"
    assert parse_tokens(client.line(), "t") == [client]


def test_the_format_one_client_a_line_with_comments_and_robot_limits():
    a, b = hashlib.sha256(b"a").hexdigest(), hashlib.sha256(b"b").hexdigest()
    text = f"# header\n\nops sha256:{a}   # the control room\n  dock-west\tsha256:{b} robots=r1,r2\n"
    assert parse_tokens(text, "t") == [
        Client("ops", bytes.fromhex(a)),
        Client("dock-west", bytes.fromhex(b), frozenset({"r1", "r2"})),
    ]
    assert parse_tokens("", "t") == []  # a file of no clients locks everyone out


@pytest.mark.parametrize(
    "line2, says",
    [
        ("dock", "expected NAME sha256:HEX"),
        ("dock gmmap_abc", "sha256: and 64 hex digits (not the token itself)"),
        ("dock sha256:" + "A" * 64, "sha256: and 64 hex digits"),  # lower-case hex only: one spelling
        ("dock sha256:" + "0" * 63, "sha256: and 64 hex digits"),
        ("do/ck sha256:" + "1" * 64, "must match"),
        ("dock sha256:" + "1" * 64 + " robot=a", "robots=ID,ID"),
        ("dock sha256:" + "1" * 64 + " robots=a,,b", "must match"),
        ("ops sha256:" + "1" * 64, "client ops is already on an earlier line"),
        ("dock sha256:" + "0" * 64, "the same token as client ops"),
        ("dock sha256:" + "1" * 64 + " robots=a extra", "got 4 words"),
    ],
)
def test_a_bad_line_is_named_by_file_and_line(tmp_path, line2, says):
    path = tmp_path / "tokens.txt"
    path.write_text(f"ops sha256:{'0' * 64}\n{line2}\n")
    with pytest.raises(ValueError, match="line 2: ") as error:
        read_tokens(path)
    assert str(path) in str(error.value) and says in str(error.value)


def test_an_unreadable_file_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"--http-tokens: cannot read .*absent.txt"):
        TokenFile(tmp_path / "absent.txt")


def test_lookup_finds_the_client_of_a_token_and_nothing_for_others(tmp_path):
    (ops, ops_client), (dock, dock_client) = new_token("ops"), new_token("dock", ["a"])
    path = tmp_path / "tokens.txt"
    path.write_text(f"{ops_client.line()}\n{dock_client.line()}\n")
    file = TokenFile(path)
    assert file.client(ops) == ops_client and file.client(dock) == dock_client
    assert file.client(dock).robots == {"a"}
    for wrong in ("", ops[:-1], ops + "x", dock_client.digest.hex(), f"sha256:{dock_client.digest.hex()}"):
        assert file.client(wrong) is None


def test_edits_apply_without_a_restart_and_a_broken_edit_keeps_the_clients(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(tokens, "RELOAD_S", 0.0)
    (old, old_client), (new, new_client) = new_token("old"), new_token("newer")
    path = tmp_path / "tokens.txt"
    path.write_text(old_client.line() + "\n")
    file = TokenFile(path)
    assert file.client(old) is not None
    path.write_text(new_client.line() + "\n")  # the old client revoked, a new one added
    assert file.client(old) is None and file.client(new) == new_client
    path.write_text(new_client.line() + "\nhalf a line\n")
    assert file.client(new) == new_client  # kept, and the error logged
    assert "keeping the 1 clients read before" in caplog.text and "line 2" in caplog.text
    path.unlink()  # between an editor's two steps
    assert file.client(new) == new_client


def test_gmmap_token_prints_the_token_and_appends_its_line(tmp_path, capsys):
    path = tmp_path / "tokens.txt"
    assert cli.main(["token", "ops", "--add", str(path)]) == 0
    token = capsys.readouterr().out.strip()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert cli.main(["token", "dock", "--robots", "a,b", "--add", str(path)]) == 0
    dock = capsys.readouterr().out.strip()
    file = TokenFile(path)
    assert file.client(token).name == "ops" and file.client(dock).robots == {"a", "b"}
    assert cli.main(["token", "ops", "--add", str(path)]) == 2  # one token per name
    assert "client ops already has a token" in capsys.readouterr().err
    assert cli.main(["token", "dock"]) == 0  # without --add: the line to add, on stderr
    printed = capsys.readouterr()
    (line,) = [li for li in printed.err.splitlines() if li.startswith("dock sha256:")]
    assert parse_tokens(line, "t")[0].digest == hashlib.sha256(printed.out.strip().encode()).digest()
    with pytest.raises(SystemExit):
        cli.main(["token", "dock", "--robots", "a,b/c"])
