"""One table of labels files, valid and not, for the two checks of one rule: the run's (`labels_problem` in the PbRL
scripts) and the page's (`label_app.parse_answers`). Both test files read it, so the two checks cannot drift apart.

The rule: a JSON list with one answer per query, each exactly the JSON token 0, 1 or 0.5, or the string "skip"; alone,
or as `{"queries": digest, "answers": list}` with the digest (16 hex digits) of the queries it answers."""

# (the file's bytes, the number of queries of its round)
VALID = [
    (b'[0, 1, 0.5, "skip"]', 4),
    (b'[1,  0, "skip"]\n', 3),  # spaces and a newline, as a person types them
    (b'[0.5]', 1),
    (b'["sk\\u0069p"]', 1),  # a JSON escape: the string is "skip"
    (b'[1,0,1,0,1,0,1,0,1,0]', 10),
    (b'{"queries": "be9af0bb37ec6d15", "answers": [0, 1, 0.5, "skip"]}', 4),  # the page's, bound to its queries
    (b'{"answers": [1], "queries": "0123456789abcdef"}', 1),
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
    (b'{"queries": "be9af0bb37ec6d15", "answers": [0, 1]}', 3),  # too few, bound or not
    (b'{"queries": "BE9AF0BB37EC6D15", "answers": [0]}', 1),  # not the digest's spelling
    (b'{"queries": "be9af0bb", "answers": [0]}', 1),  # too short
    (b'{"queries": 7, "answers": [0]}', 1),
    (b'{"queries": "be9af0bb37ec6d15", "answers": [0], "extra": 1}', 1),
    (b'"skip"', 1),
    (b"0", 1),
    (b"", 1),
    (b"[1, 2", 2),
    (b"\xff\xfe", 1),
    (b"[" * 20000 + b"]" * 20000, 1),  # deeper than json's recursion limit
]
