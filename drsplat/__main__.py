import sys

try:
    from drsplat.cli import main
except KeyboardInterrupt:  # Ctrl-C while Python imports the command line: before any command ran
    sys.stderr.write("drsplat: interrupted while starting; nothing was done\n")
    raise SystemExit(1) from None

raise SystemExit(main())
