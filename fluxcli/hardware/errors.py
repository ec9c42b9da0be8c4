"""Device errors: the CLI shows them as one paragraph and exits 2."""

from __future__ import annotations

from ..errors import UserError


def _shown(said: bytes | str | None, limit: int = 120) -> str:
    """What the device sent, printable (control bytes escaped) and cut to ``limit`` chars."""
    if said is None:
        return "nothing"
    if isinstance(said, bytes):
        text = said.decode("latin-1")
    else:
        text = said
    text = text.encode("unicode_escape").decode("ascii")
    return repr(text if len(text) <= limit else text[:limit] + "...")


class DeviceError(UserError):
    """A device did not do what it was told, or did not answer.

    Parameters
    ----------
    device : str
        Which device ("filter wheel FW102C", "stage (APT lab jack)").
    port : str
        The port or URL it is on.
    problem : str
        What went wrong, in words.
    said : bytes or str or None
        What the device sent last (shown escaped), or None when that is not relevant.
    """

    def __init__(self, device: str, port: str, problem: str, said: bytes | str | None = None,
                 *, show_said: bool = True):
        self.device = device
        self.port = port
        self.problem = problem
        self.said = said
        text = f"{device} on {port}: {problem}"
        if show_said:
            text += f" (it said: {_shown(said)})"
        if not text.endswith("."):
            text += "."
        super().__init__(text)
