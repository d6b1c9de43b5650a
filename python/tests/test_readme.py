"""The README's example runs as written (against the test server)."""

from __future__ import annotations

import os
import re
from pathlib import Path

from conftest import REPO, Server


def test_readme_example(server: Server, capsys) -> None:
    text = (REPO / "python" / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len(code.strip().splitlines()) <= 12
    code = code.replace("http://127.0.0.1:50051", server.url)
    cwd = Path.cwd()
    os.chdir(REPO)
    try:
        exec(compile(code, "README.md", "exec"), {})
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    assert "(17, 3) (16,)" in out
