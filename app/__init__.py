"""The dashboard (`gsmn serve`): a viser page and a FastAPI API around one runner thread.

runner (simulator, renderer, policies; commands in `commands`), recording (episodes in memory), viewer (the page),
scene (the 3D scene), panels (text and map panels), layers and colors (the model's maps made readable), api (HTTP),
server (wiring and URLs), cli (the `gsmn serve` subcommand), fixtures (an untrained checkpoint for tests and demos).
"""
