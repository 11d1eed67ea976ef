from drsplat.cli import main

raise SystemExit(main())
