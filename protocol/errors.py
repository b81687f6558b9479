"""The one exception type for everything that cannot cross the wire."""

from __future__ import annotations


class ProtocolError(ValueError):
    """A message, key or value that violates the wire protocol.

    `field` names where the problem is (e.g. "occupied.covariances"), so a robot-side
    developer can find it; str(error) is "<field>: <message>".
    """

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

    def __reduce__(self):  # keep picklable across processes despite the two-argument __init__
        return (type(self), (self.field, self.message))
