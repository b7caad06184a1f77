from kneemesh.cli import app

app()
