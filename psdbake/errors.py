"""One exception hierarchy, each class carrying its exit code.

The CLI maps these to one-line messages in one place (``cli.main``); the library
never prints. Messages name the file, the prim and what is wrong.
"""

from __future__ import annotations


class PsdError(Exception):
    """Base class: a clean psdbake refusal (no traceback is shown to users)."""

    exit_code = 1


class InputError(PsdError):
    """An input file, prim or attribute is missing, malformed or inconsistent."""

    exit_code = 3


class UsdDataError(InputError):
    """USD itself refused the inputs' data half-way through a command (a ``Tf.ErrorException``
    past psdbake's own checks): which input is at fault is not known where it is raised, so
    the CLI names the command's input files."""


class SettingError(InputError):
    """A setting with a bad value, named by the library's parameter (``rtol``, ``drivers``);
    the CLI shows it under its own flag (``--tolerance``, ``--driver``) with ``render``."""

    def __init__(self, param: str, value: object, problem: str, location: str = "") -> None:
        self.param, self.value, self.problem, self.location = param, value, problem, location
        super().__init__(self.render(param))

    def render(self, name: str) -> str:
        shown = f"{name} {self.value!r}" if self.value is not None else name  # no value given: the flag alone
        return f"{self.location + ': ' if self.location else ''}{shown}: {self.problem}"


class FitError(PsdError):
    """The inputs are readable but the fit is ill-posed (e.g. duplicate poses)."""

    exit_code = 4


class DeformerError(PsdError):
    """A user ``--deformer`` could not be loaded or returned bad data."""

    exit_code = 5


class OutputError(PsdError):
    """The output cannot be written (folder missing, read-only, equals an input)."""

    exit_code = 6


class StrictError(PsdError):
    """The result missed its tolerance, so nothing was written: a degraded fit (the product does
    not reproduce an example within the round-trip tolerance; ``--allow-degraded`` writes it
    anyway), or ``--strict`` and some vertex missed the fit tolerance."""

    exit_code = 7


# --- raised by one stage ------------------------------------------------------------------------


class ReportError(PsdError):
    """The report cannot be drawn (matplotlib missing)."""

    exit_code = 1


class ChunkUsageError(PsdError):
    """A chunk option that makes no sense (size below 1, chunk number out of range)."""

    exit_code = 2


class BatchUsageError(PsdError):
    """A batch option that cannot be honoured here (e.g. ``--scheduler`` without dask)."""

    exit_code = 2


class BatchError(PsdError):
    """Some jobs failed; the exit code is the first failed job's (file order)."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class SculptOutOfRangeError(ValueError):
    """A sculpted vertex lies absurdly far from its skinned position (``solver.solve`` turns it
    into an ``InputError`` naming the file and the example)."""

    def __init__(self, vertex: int, distance: float, diagonal: float) -> None:
        super().__init__(f"vertex {vertex} is {distance:.3g} away from its skinned position, far outside the mesh "
                         f"({distance / max(diagonal, 1e-300):.3g} times its size): broken data or a unit mix-up")
        self.vertex, self.distance, self.diagonal = vertex, distance, diagonal


# the live Blender rig's compiler (export/blender): defects or data it cannot express, raised
# and caught inside the compiler and its tests

class SimpleExpressionError(ValueError):
    """A text outside Blender's simple subset, or an operation that would fail the driver."""


class LayoutError(ValueError):
    """An expression that no layout fits in Blender's limit (a compiler defect, not bad data)."""


class CompileError(ValueError):
    """``psd:`` data the compiler has no building block for (a new pose space or kernel)."""


class PsdWarning(UserWarning):
    """Something users should know about that does not stop the run."""


def where(file: str | None = None, prim: str | None = None, attr: str | None = None) -> str:
    """Format a location as ``file <prim>.attr`` for error messages."""
    parts = []
    if file:
        parts.append(str(file))
    if prim:
        parts.append(f"<{prim}{'.' + attr if attr else ''}>")
    elif attr:
        parts.append(attr)
    return " ".join(parts)
