"""The dashboard (`gsmn serve`): a viser page and a FastAPI API around one runner thread.

runner (simulator, renderer, policies; commands in `commands`), recording (episodes in memory), viewer (the page;
its events in `viewer_events`), scene (the 3D scene), panels (text and map panels), layers and colors (the model's
maps made readable), api (HTTP), server (wiring and URLs), cli (the `gsmn serve` subcommand), fixtures (an untrained
checkpoint for tests and demos).

Evaluations and fine-tuning runs in their own processes: jobs (what each runs, `JobManager`), run_settings (a run's
presets and configuration), supervisor (their process groups), results (episode rows, attribution, comparisons),
db (their SQLite record), jobs_api (their HTTP routes), jobs_view (their tabs in the page; what the tabs say in
jobs_panels).
"""
