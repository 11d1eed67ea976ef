import signal
import sys

# SIGTERM while Python imports the command line is Ctrl-C there: one line, exit 1 (it killed the
# process by the signal). Python's own handler, not drsplat.cli's context manager: that is the import
# it guards; `drsplat.cli.main` takes over with it before it builds the parser.
signal.signal(signal.SIGTERM, signal.default_int_handler)
try:
    from drsplat.cli import entry
except KeyboardInterrupt:  # Ctrl-C while Python imports the command line: before any command ran
    sys.stderr.write("drsplat: interrupted while starting; nothing was done\n")
    raise SystemExit(1) from None

entry()
