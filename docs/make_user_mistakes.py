"""Regenerate docs/user_mistakes.md: every case of tests/test_user_mistakes.py with the one
paragraph fluxmap answers it with (the test itself checks the exit code and the key named).

    $ .venv/bin/python docs/make_user_mistakes.py      # ~1 min
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_CHARS = 230  # longer messages are cut, as the table is for reading


def messages() -> list[tuple[str, str]]:
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                        "tests/test_user_mistakes.py::test_user_mistake_exits_2_naming_the_key_or_file"],
                       cwd=ROOT, capture_output=True, text=True, env={**os.environ, "FLUXMAP_SHOW_MISTAKES": "1"})
    if r.returncode != 0:
        raise SystemExit(f"the mistakes' test failed; fix it first:\n{r.stdout[-3000:]}")
    found = re.findall(r"^MISTAKE (\S+) \| (.*?)(?=^MISTAKE |^\.|^\s*$|\Z)", r.stdout, flags=re.M | re.S)
    return [(name, _short(text)) for name, text in found]


def _short(text: str) -> str:
    text = " ".join(text.split()).removeprefix("fluxmap: error: ")
    tmp = r"(?:/[^\s/]+)*/pytest-of-[^/\s]+/pytest-\d+/[^/\s]+"  # the case's own folder
    text = re.sub(tmp + "/", "", text)  # its files, by their names
    text = re.sub(tmp, "DIR", text)  # the folder itself
    text = re.sub(r"^config cfg\.yaml: ", "", text)  # the config's name, said by every key's message
    return text if len(text) <= MAX_CHARS else text[:MAX_CHARS].rstrip() + " ..."


def main() -> None:
    rows = messages()
    lines = ["# User mistakes and what fluxmap says (generated from tests/test_user_mistakes.py)", "",
             "Each exits 2 with this one paragraph and no traceback (paths shortened). Made by",
             "`docs/make_user_mistakes.py`.", "", "| mistake | message (excerpt) |", "|---|---|"]
    lines += [f"| {name} | {text.replace('|', '/')} |" for name, text in rows]
    (ROOT / "docs" / "user_mistakes.md").write_text("\n".join(lines) + "\n")
    print(f"docs/user_mistakes.md: {len(rows)} mistakes")


if __name__ == "__main__":
    main()
