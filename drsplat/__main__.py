from drsplat.console import entry

entry()
