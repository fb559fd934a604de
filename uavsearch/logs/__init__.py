"""Flight logs: recording (tlog + search.jsonl) and replay."""
