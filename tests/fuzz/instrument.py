"""Third-party packages whose parsers a target also instruments (coverage inside them guides
the search towards inputs that get through them to ours)."""
EXTRA = {
    "mavlink": ["pymavlink"],
    "j1939": ["cantools", "can"],
    "console": ["http", "email"],       # the stdlib's request-line and header parsing
}
