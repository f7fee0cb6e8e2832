"""The exceptions a command turns into one line on stderr: a user's mistake, or the machine's."""


class ConfigError(ValueError):
    """A user-fixable mistake; its message is one line that names the bad value and what is allowed."""


class RunError(RuntimeError):
    """The machine or the cluster failed a command (a full disk, a SLURM command that failed); its message is
    one line that says what happened to the work and what to do."""


def damaged_file(path: object, error: Exception) -> ConfigError:
    """The one-line error for a sweep file that cannot be read."""
    return ConfigError(f"{path} cannot be read ({type(error).__name__}: {' '.join(str(error).split())[:120]}); the "
                       "sweep directory is damaged: restore that file, or launch the sweep into a new sweep_dir")
