"""Errors a user can cause (exit 2) and simulation divergence (exit 3)."""
import difflib


class UserError(Exception):
    """Bad input: a scene key, a file, an option. The message is one line naming what is wrong."""

    exit_code = 2


class DivergenceError(Exception):
    """The simulation left its physical bounds; what was recorded so far is kept."""

    exit_code = 3


class Terminated(KeyboardInterrupt):
    """SIGTERM (a job manager, `timeout`, `kill`): handled like Ctrl-C, so the run folder is closed and kept."""

    exit_code = 143  # 128 + SIGTERM


def did_you_mean(word, options) -> str:
    """' (did you mean 'x'?)' for the option closest to a misspelt word, or ''."""
    if not isinstance(word, str):
        return ""
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""
