"""The compensator's errors, shared by every front end (OPC UA client and station, the
LinuxCNC component) and the I/O-free cycle logic (:mod:`.control`)."""

from __future__ import annotations


class CompensatorError(ValueError):
    """A compensator set-up that cannot work (names the config key, file or node)."""


class RefusedWrite(Exception):
    """The compensator was asked to write a node that is not one of its configured outputs
    (a programming error: never taken for a lost connection)."""
