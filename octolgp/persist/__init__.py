"""The single-file map (SQLite): the only module that reads and writes map files."""
