"""Exit statuses shared by every command of the project (mapex, services, deploy)."""

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran but did not produce what it was asked for
EXIT_USAGE = 2  # bad flags or input, found before any work: one line on stderr
EXIT_INTERRUPTED = 130  # Ctrl-C / SIGINT
