import signal
import sys


def _interrupt(signum, frame):
    raise KeyboardInterrupt


# SIGTERM while Python imports the command line is Ctrl-C there: one line, exit 1 (it killed the
# process by the signal; `drsplat.cli.main` takes over before it builds the parser)
signal.signal(signal.SIGTERM, _interrupt)
try:
    from drsplat.cli import entry
except KeyboardInterrupt:  # Ctrl-C while Python imports the command line: before any command ran
    sys.stderr.write("drsplat: interrupted while starting; nothing was done\n")
    raise SystemExit(1) from None

entry()
