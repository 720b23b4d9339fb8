"""argparse types for userctl's numeric and address arguments: a bad value is a one-line error naming the argument,
not a traceback."""

from __future__ import annotations

import argparse
import math


def integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text.strip()!r} is not an integer") from None


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """An integer >= 0 (a seed, an index)."""
    value = integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text.strip()!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def host_port(text: str) -> str:
    """A gRPC target HOST:PORT (an IPv6 address in brackets: [::1]:50051) with a port in 1-65535, returned
    as given. Checked here because gRPC takes the port modulo 65536 and turns an empty target into log noise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT")
    if host.startswith("["):
        if not host.endswith("]") or len(host) == 2:
            raise argparse.ArgumentTypeError(f"{text!r}: bad bracketed IPv6 host {host!r}")
    elif ":" in host:
        raise argparse.ArgumentTypeError(f"{text!r}: put an IPv6 address in brackets, e.g. [::1]:50051")
    if any(c.isspace() or c in "/[]" for c in host.strip("[]")):
        raise argparse.ArgumentTypeError(f"{text!r}: {host!r} is not a host name or address")
    if not port:
        raise argparse.ArgumentTypeError(f"{text!r} has no port (HOST:PORT)")
    if not (port.isascii() and port.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r}: port {port!r} is not a number")
    if not 1 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: port {int(port)} is outside 1-65535")
    return text
