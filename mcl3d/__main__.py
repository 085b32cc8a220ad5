from mcl3d.cli import app

app(prog_name="mcl3d")
