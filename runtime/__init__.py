"""Process runtime: settings models from flags, FEDRL_* variables and .env files; logging and exit codes."""
