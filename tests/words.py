"""What must never reach a person in a command's human output: a Python dict or list repr,
None, True or False, an epoch time in seconds. One pattern for every command's test."""

from __future__ import annotations

import re

PYTHON_REPR = re.compile(r"\{'|\['|\bNone\b|\bTrue\b|\bFalse\b|\b1[6-9]\d{8}(\.\d+)?\b")
