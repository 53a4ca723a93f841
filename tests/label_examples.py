"""One table of labels files, valid and not, for the two checks of one rule: the run's (`labels_problem` in the PbRL
scripts) and the page's (`label_app.parse_answers`). Both test files read it, so the two checks cannot drift apart.

The rule: a JSON list with one answer per query, each exactly the JSON token 0, 1 or 0.5, or the string "skip"."""

# (the file's bytes, the number of queries of its round)
VALID = [
    (b'[0, 1, 0.5, "skip"]', 4),
    (b'[1,  0, "skip"]\n', 3),  # spaces and a newline, as a person types them
    (b'[0.5]', 1),
    (b'["sk\\u0069p"]', 1),  # a JSON escape: the string is "skip"
    (b'[1,0,1,0,1,0,1,0,1,0]', 10),
]

INVALID = [
    (b"[true]", 1),  # Python counts true as 1
    (b"[false]", 1),  # and false as 0
    (b"[1e0]", 1),
    (b"[-0.0]", 1),
    (b"[-0]", 1),
    (b"[1.0]", 1),
    (b"[0.0]", 1),
    (b"[0.50]", 1),
    (b"[5e-1]", 1),
    (b"[0.50000000000000001]", 1),  # the float 0.5, but not the token
    (b"[NaN]", 1),
    (b"[Infinity]", 1),
    (b"[null]", 1),
    (b"[2]", 1),
    (b'["Skip"]', 1),
    (b'["0.5"]', 1),
    (b"[[0]]", 1),
    (b"[{}]", 1),
    (b"[1, 0]", 3),  # too few
    (b"[1, 0, 1, 0]", 3),  # too many
    (b'{"answers": [0]}', 1),
    (b'"skip"', 1),
    (b"0", 1),
    (b"", 1),
    (b"[1, 2", 2),
    (b"\xff\xfe", 1),
    (b"[" * 20000 + b"]" * 20000, 1),  # deeper than json's recursion limit
]
