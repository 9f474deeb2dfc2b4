"""Errors a user can cause (exit 2) and simulation divergence (exit 3)."""


class UserError(Exception):
    """Bad input: a scene key, a file, an option. The message is one line naming what is wrong."""

    exit_code = 2


class DivergenceError(Exception):
    """The simulation left its physical bounds; what was recorded so far is kept."""

    exit_code = 3


class Terminated(KeyboardInterrupt):
    """SIGTERM (a job manager, `timeout`, `kill`): handled like Ctrl-C, so the run folder is closed and kept."""

    exit_code = 143  # 128 + SIGTERM
