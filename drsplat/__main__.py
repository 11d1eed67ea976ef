import sys

try:
    from drsplat.cli import entry
except KeyboardInterrupt:  # Ctrl-C while Python imports the command line: before any command ran
    sys.stderr.write("drsplat: interrupted while starting; nothing was done\n")
    raise SystemExit(1) from None

entry()
