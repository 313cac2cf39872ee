"""Configuration: the schema (dataclasses), its checks and TOML loading."""
