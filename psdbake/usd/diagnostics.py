"""USD's diagnostics, turned into psdbake's one-line messages.

USD reports problems as C++ diagnostics (printed to stderr unless trapped) and as
``Tf.ErrorException`` texts that carry C++ source locations; users get neither: the CLI
shows one line per problem, naming the file and what is wrong.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator

from pxr import Tf

from ..errors import UsdDataError


def first_line(exc: BaseException | str) -> str:
    """USD's message without its C++ source location ("Error in '...' at line N in file ...")."""
    try:
        text = str(exc).strip()
    except UnicodeDecodeError:  # USD's message quotes the file's own bytes, which are not UTF-8
        return "it holds text that is not UTF-8"
    quoted = re.findall(r" : '(.*?)'\s*(?:\n|$)", text, flags=re.S)
    if quoted:
        text = quoted[-1]
    # the text parser names the C++ grammar rule it expected: say where, not what type
    text = re.sub(r"parse error matching .*? at '", "parse error at '", text, flags=re.S)
    text = re.sub(r"parse error matching .*", "parse error", text, flags=re.S)
    text = re.sub(r"pxrInternal_v\w*?__pxrReserved__\w*::", "", text)  # USD's C++ namespace, e.g. in type names
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if len(lines) > 1 and lines[0].endswith(":"):  # e.g. "Cycle detected:" then the arcs of the cycle
        return re.sub(r",?@anon:[^@]*@,?", "", " ".join(lines))  # without psdbake's and USD's in-memory layers
    return lines[0] if lines else type(exc).__name__


@contextlib.contextmanager
def usd_diagnostics() -> Iterator[list[str]]:
    """Trap USD's own warnings and errors (printed from C++ otherwise) and hand back their
    one-line texts, so the CLI decides what users see."""
    found: list[str] = []
    with Tf.DiagnosticTrap() as trap:
        try:
            yield found
        finally:
            for diagnostic in list(trap.GetWarnings()) + list(trap.GetStatuses()) + list(trap.GetErrors()):
                found.append(first_line(getattr(diagnostic, "commentary", "") or str(diagnostic)))
            trap.Clear()


@contextlib.contextmanager
def usd_errors() -> Iterator[None]:
    """A ``Tf.ErrorException`` that escapes psdbake's own checks (USD refusing corrupt or
    inconsistent data) becomes a ``UsdDataError`` (bad input, exit 3), not an internal error."""
    try:
        yield
    except Tf.ErrorException as exc:
        raise UsdDataError(f"USD could not use the data ({first_line(exc)})") from None
