# SPDX-License-Identifier: Apache-2.0
"""The root of ISAC Twin's error hierarchy, and the contract's own errors.

Standard library only. The engine's errors (:mod:`isac_twin.errors`) derive from
:class:`IsacTwinError` too, so one ``except IsacTwinError`` catches every error the
project raises on purpose, on either side of the contract.
"""

from __future__ import annotations

__all__ = ["IsacTwinError", "ContractError"]


class IsacTwinError(Exception):
    """Base of every error ISAC Twin raises on purpose: the message says what was
    wrong (file, key, byte or name) and what was expected."""


class ContractError(IsacTwinError, ValueError):
    """Something the add-on and the engine exchange breaks the contract: a scene
    folder's vocabulary or a live-link message."""
