"""Tabulate trial.py results: stuck restarts and first-receive times per setup.

    python summarize.py [results.jsonl ...]   (default: the results_*.jsonl here)

Groups the trials by tag, transport (the profile's file name for records that
carry one), rate, down time, --busy, --sub-first and the reader's user-data
listener state at the kill (waiting, processing, NEITHER = the fault's window,
or n/a without a shared-memory user-data port), and prints per group how many
restarts were stuck and the first-receive times (s after the restart) of the
others. summary_2026-12-07.txt is its output for results_2026-12-07.jsonl.
"""

from collections import defaultdict
import json
from pathlib import Path
import sys

USER_PORT_MIN = 40000


def listener_class(record):
    user = [v for k, v in record['state_at_kill'].items() if int(k) > USER_PORT_MIN]
    if not user or not isinstance(user[0], dict):
        return 'n/a(udp)'
    return 'waiting' if user[0]['w'] else 'processing' if user[0]['p'] else 'NEITHER'


def transport(record):
    if 'profile' in record:   # trial.py's records: the profile in use
        return Path(record['profile']).name if record['profile'] else 'env default'
    if 'udpxml' in record['transport']:   # the 2026-12-07 records
        return 'UDPxml'
    return 'envUDPv4(SHM still on)' if record['transport'] == 'UDPv4' else 'SHM+UDP'


def load(paths):
    for path in paths:
        with open(path) as f:
            yield from (json.loads(line) for line in f if line.strip())


def main():
    here = Path(__file__).resolve().parent
    paths = sys.argv[1:] or sorted(here.glob('results_*.jsonl'))
    groups = defaultdict(list)
    for record in load(paths):
        if 'trial' in record:   # not a state-sampling line
            key = (record['tag'], transport(record), record['rate'], record['down'],
                   record['busy'], record['sub_first'], listener_class(record))
            groups[key].append(record)
    width = max([23] + [len(key[1]) for key in groups])
    print(f'{"tag":24s} {"transport":{width}s} {"rate":>5s} {"down":>5s} busy subfirst '
          f'{"listener@kill":13s} stuck/n  first_rx(s) of recovered')
    for (tag, kind, rate, down, busy, sub_first, cls), records in groups.items():
        stuck = sum(1 for r in records if r['stuck'])
        first_rx = [r['first_rx'] for r in records if not r['stuck']]
        print(f'{tag:24s} {kind:{width}s} {rate:5.0f} {down:5.1f} {str(busy):5s} '
              f'{str(sub_first):5s}    {cls:13s} {stuck}/{len(records)}   {first_rx}')


if __name__ == '__main__':
    main()
