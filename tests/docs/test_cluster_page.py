"""The cluster page's plain-tcp section says what the loopback does not protect against."""

from pathlib import Path

PAGE = Path(__file__).resolve().parents[2] / "docs" / "cluster.md"


def test_the_loopback_section_says_local_users_can_run_code_and_what_to_do():
    text = PAGE.read_text()
    section = " ".join(text.split("## Plain `tcp://` on the loopback only", 1)[1].split("\n## ", 1)[0].split())
    assert "any local user" in section and "run code on them" in section
    assert "use `tls://` with the certificates above even on the loopback" in section
    assert "a machine only you use" in section
