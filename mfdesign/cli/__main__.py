from mfdesign.cli import app

app()
