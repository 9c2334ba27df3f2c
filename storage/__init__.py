"""jitdyn's storage: every session's frames as Parquet, crash-safe while it runs, indexed in SQL.

records    TickRecord, SessionHeader, SessionSummaryInfo: the values stored
recorder   SessionRecorder (one session: log, group commit, compaction), recover_unfinished
index      SessionIndex over the SQL `sessions` table (db.open_index, schema, migrations/)
anonymise  pseudonyms (HMAC-SHA256) and the attribute allow-list; the server secret
query      run_query: DuckDB over the Parquet files and the index
export     export_session: CSV and OpenSim .sto
columns, parquet, log, layout, summary: the file formats and paths underneath
"""
