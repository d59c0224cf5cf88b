"""The demo's pieces in short form: three nodes, swaps, an MCAP of every topic, a plot."""

import json
import subprocess
import sys

from conftest import REPO
from mcap_ros2.reader import read_ros2_messages
from zeus_ros.demo import RECORDED_TOPICS


def test_short_demo_records_every_topic_and_plots(small_checkpoint, tmp_path):
    out = tmp_path / 'demo_out'
    result = subprocess.run(
        [sys.executable, '-m', 'zeus_ros.demo', '--weights', str(small_checkpoint),
         '--steps', '150', '--schedule', '0:1.0,50:0.4,100:1.7', '--out', str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'total return' in result.stdout
    assert 'not received' not in result.stdout, result.stdout   # every step recorded

    counts, friction_seen = dict.fromkeys(RECORDED_TOPICS, 0), set()
    for message in read_ros2_messages(out / 'demo.mcap'):
        counts[message.channel.topic] += 1
        if message.channel.topic == '/zeus/step':
            friction_seen.add(message.ros_msg.param_values[0])
    assert all(n > 0 for n in counts.values()), counts
    assert counts['/zeus/step'] >= 150
    assert {1.0, 0.4, 1.7} <= friction_seen

    segments = json.loads((out / 'segments.json').read_text())
    assert [s['true'] for s in segments] == [1.0, 0.4, 1.7]
    assert sum(s['steps'] for s in segments) >= 150
    png = (out / 'demo.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 10_000


def test_demo_and_bringup_refuse_missing_weights_in_one_line(tmp_path):
    for module in ('zeus_ros.demo', 'zeus_ros.bringup'):
        result = subprocess.run([sys.executable, '-m', module, '--weights', str(tmp_path)],
                                cwd=REPO, capture_output=True, text=True, timeout=60)
        assert result.returncode == 1
        assert f'no checkpoint at {tmp_path}' in result.stderr
        assert 'Traceback' not in result.stderr
