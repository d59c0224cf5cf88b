"""Read a Fast DDS 2.14 shared-memory port segment and print its state.

    python shmstat.py /dev/shm/fastrtps_port45163 [/proc/PID/map_files/RANGE ...]

A segment is a file in /dev/shm or, once unlinked, a process's still-mapped
copy under /proc/PID/map_files/. It prints the PortNode fields (is_port_ok,
num_listeners, waiting_count, ...), the ring buffer's free cells and, per
listener slot in use, its waiting/processing flags. trial.py and freeze_kill.py
import the readers below.

The layout was found empirically on Fast DDS 2.14.5 (x86_64): the 1024
listener status slots (20 bytes each) end right before the domain name
'fastrtps' and its NUL byte, and PortNode.port_id sits 20612 bytes before the first slot.
"""

import re
import struct
import sys

SLOTS = 1024
SLOT_SIZE = 20
PORT_ID_BEFORE_SLOTS = 20612
READ_ERRORS = (OSError, ValueError, IndexError, struct.error)


def segment_path(port):
    return f'/dev/shm/fastrtps_port{port}'


def listener_slots(data, base):
    """Return the listener slots in use, starting at offset BASE of DATA."""
    slots = []
    for k in range(SLOTS):
        flags, counters = data[base + SLOT_SIZE * k], data[base + SLOT_SIZE * k + 1]
        if flags & 1:
            slots.append(dict(slot=k, in_use=1, waiting=(flags >> 1) & 1,
                              processing=(flags >> 2) & 1, counter=counters & 0xF,
                              last_verified=counters >> 4))
    return slots


def stat(path):
    """Parse the segment at PATH into a dict; raise ValueError if it is not one."""
    with open(path, 'rb') as f:
        data = f.read()
    name = data.find(b'fastrtps\x00')
    if name < 0:
        raise ValueError(f'{path}: no Fast DDS port segment')
    base = name - SLOTS * SLOT_SIZE
    node = base - PORT_ID_BEFORE_SLOTS
    (last_check,) = struct.unpack_from('<q', data, node - 20)
    (ref, _buf, node_off, port, listeners, _hc, _pw, _mb, waiting,
     bits) = struct.unpack_from('<IIIIIIIIII', data, node - 12)
    out = dict(port=port, ref=ref, num_listeners=listeners, waiting_count=waiting,
               port_ok=bits & 1, excl=(bits >> 1) & 1, reading=(bits >> 2) & 1,
               last_check_ms=last_check)
    try:   # the ring buffer node: write pointer, free cells, total cells, listeners
        _wp, free, total, registered = struct.unpack_from('<IIII', data, node_off)
        out.update(free_cells=free, total_cells=total, reg_listeners=registered)
    except struct.error:
        pass
    out['listeners'] = listener_slots(data, base)
    return out


def listener_state(port):
    """Return the first listener slot in use of PORT's segment, or None."""
    try:
        slots = stat(segment_path(port))['listeners']
    except READ_ERRORS:
        return None
    return slots[0] if slots else None


def port_summary(port):
    """Summarize PORT's segment in the short keys of the results files (a string on error)."""
    try:
        seg = stat(segment_path(port))
    except READ_ERRORS as e:
        return str(e)
    slot = seg['listeners'][0] if seg['listeners'] else {}
    return dict(port_ok=seg['port_ok'], free=seg.get('free_cells'), nl=seg['num_listeners'],
                w=slot.get('waiting'), p=slot.get('processing'), c=slot.get('counter'),
                lv=slot.get('last_verified'))


def deleted_copy(pid, port):
    """Parse process PID's mapping of PORT's unlinked segment (None: no such mapping)."""
    try:
        with open(f'/proc/{pid}/maps') as f:
            for line in f:
                if re.search(rf'fastrtps_port{port} \(deleted\)$', line.rstrip()):
                    return stat(f'/proc/{pid}/map_files/{line.split()[0]}')
    except READ_ERRORS as e:
        return str(e)
    return None


if __name__ == '__main__':
    for arg in sys.argv[1:]:
        print(arg, stat(arg))
