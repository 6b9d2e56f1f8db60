"""Rule ``report_pdf``: ``results/{subject}/report.pdf``, the study report printed by headless
Chromium.

The printed page is what ``print.css`` keeps of ``report.html``: the one-page summary (sessions'
coverage, the wall seen per standard region, each change with its region, clock, distance from
the neck and size), then one page per change card (crops before / after, region, clock, size,
the frames that show it, its size through the sessions). Chromium prints the HTML file as it
is, offline (every host name resolves to nothing), with its own empty profile; no header or
footer. Without Chromium the rule fails with :class:`~cystomap.errors.StageError` naming the
executable it looked for and how to install it.
"""

from __future__ import annotations

import logging
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from cystomap.errors import InputError, StageError
from cystomap.outputs import atomic_file

log = logging.getLogger(__name__)

TIMEOUT_S = 300  # a report of about 10 MB prints in seconds; this only stops a hung browser
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage", "--no-pdf-header-footer",
         "--host-resolver-rules=MAP * ~NOTFOUND")
PAGE = re.compile(rb"/Type\s*/Page(?![A-Za-z])")


def find_chromium(chromium: str = "chromium") -> str:
    """The Chromium executable: ``chromium`` as a path or a name on PATH."""
    found = shutil.which(chromium)
    if found is None:
        raise StageError(
            f"report.pdf needs headless Chromium, and {chromium!r} (config report.chromium) is not found: "
            "`make browser` installs Debian's chromium (apt-get install chromium); or set report.chromium "
            "to its path. report.html does not need it.")
    return found


def pdf_pages(data: bytes) -> int:
    """Pages of a PDF (its ``/Type /Page`` objects: Chromium writes them uncompressed)."""
    if not data.startswith(b"%PDF-") or b"%%EOF" not in data[-1024:]:
        raise StageError("not a complete PDF file")
    return len(PAGE.findall(data))


def print_pdf(html_path: Path, out_pdf: Path, chromium: str = "chromium") -> int:
    """Print ``html_path`` to ``out_pdf`` (atomically) with headless Chromium; the page count."""
    html_path, out_pdf = Path(html_path), Path(out_pdf)
    if not html_path.is_file():
        raise InputError(f"report.pdf: {html_path} not found")
    exe = find_chromium(chromium)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="cystomap-chromium-") as profile, atomic_file(out_pdf) as tmp:
        cmd = [exe, *FLAGS, f"--user-data-dir={profile}", f"--print-to-pdf={tmp}", html_path.resolve().as_uri()]
        try:
            run = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired as exc:
            raise StageError(f"report.pdf: {exe} did not finish printing {html_path} in {TIMEOUT_S} s") from exc
        data = tmp.read_bytes() if tmp.is_file() else b""
        if run.returncode != 0 or not data:
            tail = "\n".join((run.stderr or "").strip().splitlines()[-5:])
            raise StageError(f"report.pdf: {exe} exited with {run.returncode} and wrote {len(data)} bytes "
                             f"printing {html_path}: {tail}")
        pages = pdf_pages(data)
    log.info("report.pdf: %s, %d page(s), %.1f MB in %.1f s", out_pdf, pages, len(data) / 1e6,
             time.perf_counter() - t0)
    return pages
