from kneemesh.cli import entry

entry()
