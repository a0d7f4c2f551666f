"""Errors a user caused (a bad file, argument or model): `fcemu` prints them as one line, exit 2."""

from __future__ import annotations


class UserError(Exception):
    """Something the user gave cannot be used; the message says what and why, in one line."""
