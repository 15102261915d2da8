"""Message definitions as data: state-machine enums per ``sm_type``, protocol dialects."""
