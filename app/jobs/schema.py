"""The dashboard record's tables (SQLite) and their version; `app.jobs.db` opens, upgrades and reads them."""

SCHEMA_VERSION = 6  # 2: evaluations.mirror_ensemble; 3: episodes.region_steps and region_stop_p (an older
# record gains the columns on opening: 0 for mirror_ensemble, NULL, "not known", for the region); 4: the tables
# kept_episodes and kept_steps (every episode flown in the page or over the API, app.jobs.kept; an older record gains
# them empty); 5: the table episode_facts (each evaluated episode's slice attributes and map readings,
# gsmn.analysis.slices; an older record gains it empty, and its evaluations' facts are computed when first analysed);
# 6: evaluations.intervention (the map intervention it flew with, gsmn eval --intervene; NULL in older rows: none)

SCHEMA = """
CREATE TABLE IF NOT EXISTS evaluations (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    status TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    system TEXT NOT NULL,
    checkpoint TEXT,
    env_ids TEXT NOT NULL,          -- JSON list, in the order flown
    label TEXT NOT NULL,
    baseline_id INTEGER,            -- the evaluation whose episodes this one reruns (before/after)
    run_id INTEGER,                 -- the fine-tuning run whose checkpoint this evaluates
    source TEXT NOT NULL,           -- 'dashboard' or 'import'
    folder TEXT,
    pid INTEGER,
    command TEXT,                   -- JSON list
    done INTEGER NOT NULL DEFAULT 0,
    total INTEGER NOT NULL,
    summary TEXT,                   -- JSON: gsmn.task.metrics.Summary.to_dict()
    error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    mirror_ensemble INTEGER NOT NULL DEFAULT 0, -- flown as a test-time mirror ensemble (gsmn eval --mirror-ensemble)
    intervention TEXT               -- the map intervention it flew with (gsmn eval --intervene FLAG); NULL: none
);
CREATE TABLE IF NOT EXISTS episodes (
    evaluation_id INTEGER NOT NULL REFERENCES evaluations(id),
    position INTEGER NOT NULL,
    env_id INTEGER NOT NULL,
    instruction TEXT NOT NULL,
    landmark TEXT NOT NULL,
    side TEXT NOT NULL,
    ambiguous INTEGER NOT NULL,
    success INTEGER NOT NULL,
    landmark_success INTEGER NOT NULL,
    goal_distance REAL NOT NULL,
    steps INTEGER NOT NULL,
    stopped INTEGER NOT NULL,
    final_x REAL NOT NULL,
    final_y REAL NOT NULL,
    stage TEXT,                     -- attribution stage of a failure (NULL: success, or no maps recorded)
    attribution TEXT,               -- JSON: gsmn.attribution.Attribution.to_dict()
    recording TEXT,                 -- the episode's ModelTrace (.npz), when recorded
    region_steps TEXT,              -- JSON list: the steps inside the success region (NULL: not known)
    region_stop_p REAL,             -- the model's highest P(stop) at those steps (NULL: not recorded, or none)
    PRIMARY KEY (evaluation_id, env_id)
);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    status TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    settings TEXT NOT NULL,         -- JSON: app.jobs.settings.RunSettings
    env_ids TEXT,                   -- JSON list, or NULL for the train split
    source_evaluation_id INTEGER,   -- the evaluation whose failures it trains on
    init_checkpoint TEXT NOT NULL,
    folder TEXT NOT NULL,
    pid INTEGER,
    command TEXT,
    progress TEXT,                  -- JSON: where the run is now
    metrics TEXT,                   -- JSON list: one record per finished iteration (the run's log.jsonl)
    checkpoint TEXT,
    error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS episodes_by_evaluation ON episodes (evaluation_id, position);
CREATE TABLE IF NOT EXISTS kept_episodes (  -- an episode flown in the page or over the API (app.jobs.kept)
    id INTEGER PRIMARY KEY AUTOINCREMENT,  -- the runner's episode id: never reused, also after a removal
    created REAL NOT NULL,          -- unix time it started flying
    finished REAL,
    status TEXT NOT NULL,           -- running, paused, finished, cancelled, failed
    env_id INTEGER NOT NULL,
    split TEXT NOT NULL,
    instruction TEXT NOT NULL,
    task TEXT NOT NULL,             -- JSON: the parsed instruction and the demonstration path
    policy TEXT NOT NULL,
    system TEXT NOT NULL,
    checkpoint TEXT,
    horizon INTEGER NOT NULL,
    steps INTEGER NOT NULL DEFAULT 0,
    success INTEGER,                -- NULL until it finishes
    result TEXT,                    -- JSON: app.live.recording.EpisodeResult
    error TEXT,
    pinned INTEGER NOT NULL DEFAULT 0,
    bytes INTEGER NOT NULL DEFAULT 0  -- the stored size of its steps (camera JPEGs, quantised maps, numbers)
);
CREATE TABLE IF NOT EXISTS kept_steps (
    episode_id INTEGER NOT NULL,
    step INTEGER NOT NULL,
    data TEXT NOT NULL,             -- JSON: pose, actions, P(stop), T_world_camera, the model's own action
    camera BLOB NOT NULL,           -- JPEG
    maps BLOB,                      -- the model's maps, quantised to 8 bits per channel (app.jobs.kept_store.pack_maps)
    PRIMARY KEY (episode_id, step)
);
CREATE INDEX IF NOT EXISTS kept_by_created ON kept_episodes (created);
CREATE TABLE IF NOT EXISTS episode_facts (  -- derived from an episode, its world and its maps: kept, not recomputed
    evaluation_id INTEGER NOT NULL,
    env_id INTEGER NOT NULL,
    facts TEXT NOT NULL,            -- JSON: gsmn.analysis.slices.episode_facts
    PRIMARY KEY (evaluation_id, env_id)
);
"""
