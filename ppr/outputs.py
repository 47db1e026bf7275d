"""Results that appear whole or not at all: :func:`outputs` stages a command's files in a
hidden folder beside ``--out``, validates them and swaps them in under a journal, so a failed
or interrupted run leaves the previous result as it was (used by the ``ppr`` commands and by
:meth:`inversion.Inversion.write`); :func:`provenance` is the versions/config record every
JSON output carries."""

from ._outputs import (
    OutputError,
    Outputs,
    atomic_write_text,
    outputs,
    provenance,
    recover,
    refuse_existing,
)

__all__ = [
    "OutputError",
    "Outputs",
    "atomic_write_text",
    "outputs",
    "provenance",
    "recover",
    "refuse_existing",
]
