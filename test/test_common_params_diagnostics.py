"""The shared parameter table and diagnostics updater, on real rclpy nodes."""

from diagnostic_msgs.msg import DiagnosticArray
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from uav_serial_common.diagnostics import DiagnosticsUpdater, ERROR, OK, WARN
from uav_serial_common.logs import Throttle
from uav_serial_common.params import (check_values, declare_and_check, declare_parameters,
                                      ParameterBinding, ParamSpec)

SPECS = (
    ParamSpec('policy', 'confirm', 'what to answer', choices=('confirm', 'deny', 'defer')),
    ParamSpec('threshold', -1, 'desired threshold', int_range=(-1, 90),
              check=lambda v: '' if v == -1 or v >= 10 else f'threshold must be >= 10, got {v}'),
    ParamSpec('ids', Parameter.Type.INTEGER_ARRAY, 'servo ids', startup_only=True),
    ParamSpec('port', '/dev/null', 'port', read_only=True),
)


def make_node(ros, name):
    node = Node(name, context=ros.context)
    ros.executor.add_node(node)
    return node


def test_declared_with_descriptors_and_arrays_default_to_empty(ros):
    node = make_node(ros, 'params_declared')
    values = declare_parameters(node, SPECS)
    assert values == {'policy': 'confirm', 'threshold': -1, 'ids': [], 'port': '/dev/null'}
    desc = node.describe_parameter('policy')
    assert desc.additional_constraints == 'one of: confirm, deny, defer'
    assert node.describe_parameter('threshold').integer_range[0].to_value == 90
    assert node.describe_parameter('port').read_only
    assert check_values(SPECS, {'policy': 'maybe', 'threshold': 5}) == [
        "policy must be one of confirm, deny, defer, got 'maybe'",
        'threshold must be >= 10, got 5']


def test_a_node_given_bad_values_refuses_to_start_naming_every_one(ros):
    node = Node('params_refused', context=ros.context, parameter_overrides=[
        Parameter('policy', value='maybe'), Parameter('threshold', value=5)])
    try:
        with pytest.raises(ValueError) as refused:
            declare_and_check(node, SPECS)
        assert str(refused.value) == ("policy must be one of confirm, deny, defer, got 'maybe'; "
                                      'threshold must be >= 10, got 5')
    finally:
        node.destroy_node()


def test_a_set_is_checked_whole_before_anything_is_committed_or_applied(ros):
    node = make_node(ros, 'params_atomic')
    declare_parameters(node, SPECS)
    committed, applied = [], []

    def commit(changes):
        committed.append(changes)
        return (changes.get('threshold') != 70, 'module did not confirm threshold 70')

    ParameterBinding(node, SPECS, apply=applied.append, commit=commit)
    # One bad value refuses the whole set: the good one is neither committed nor applied.
    result = node.set_parameters_atomically([Parameter('policy', value='deny'),
                                             Parameter('threshold', value=5)])
    assert not result.successful and 'threshold must be >= 10' in result.reason
    assert committed == [] and applied == []
    # A refused commit changes nothing either, the policy included.
    result = node.set_parameters_atomically([Parameter('policy', value='deny'),
                                             Parameter('threshold', value=70)])
    assert not result.successful and result.reason == 'module did not confirm threshold 70'
    assert applied == [] and node.get_parameter('policy').value == 'confirm'
    # An accepted set is applied once, whole.
    result = node.set_parameters_atomically([Parameter('policy', value='deny'),
                                             Parameter('threshold', value=40)])
    assert result.successful
    assert applied == [{'policy': 'deny', 'threshold': 40}]
    # Start-only parameters are refused with the reason.
    result = node.set_parameters([Parameter('ids', value=[1, 2])])[0]
    assert not result.successful and 'read at start only' in result.reason


def test_diagnostics_names_carry_the_namespace_and_force_update_is_prompt(ros):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    node = Node('parachute', namespace='uav7', context=ros.context)
    ros.executor.add_node(node)
    state = {'level': OK, 'text': 'fine'}

    def link(stat):
        stat.summary(state['level'], state['text'])
        stat.add('frames', 12)

    def broken(stat):
        raise RuntimeError('bug')

    updater = DiagnosticsUpdater(node, '/dev/ttyUSB9', period_s=30.0)
    updater.add('link', link)
    updater.add('broken', broken)
    updater.force_update()
    msg = diags.wait(lambda m: any(s.name == '/uav7/parachute: link' for s in m.status), 5)
    link_status = next(s for s in msg.status if s.name == '/uav7/parachute: link')
    assert link_status.hardware_id == '/dev/ttyUSB9' and link_status.message == 'fine'
    assert [(kv.key, kv.value) for kv in link_status.values] == [('frames', '12')]
    broken_status = next(s for s in msg.status if s.name == '/uav7/parachute: broken')
    assert broken_status.level == ERROR and 'bug' in broken_status.message
    # A change forced twice in a row is published (the second within min_interval_s),
    # long before the 30 s period.
    start = len(diags)
    state.update(level=WARN, text='warned')
    updater.force_update()
    state.update(level=ERROR, text='offline')
    updater.force_update()
    diags.wait(lambda m: any(s.name.endswith(': link') and s.message == 'offline'
                             and s.level == ERROR for s in m.status), 5, start=start)


def test_a_removed_task_is_no_longer_published(ros):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    node = make_node(ros, 'servo_bus_removal')
    updater = DiagnosticsUpdater(node, '/dev/ttyUSB9', period_s=30.0)
    updater.add('bus', lambda stat: stat.summary(OK, 'fine'))
    updater.add('servo_3 (id 3)', lambda stat: stat.summary(OK, 'fine'))
    updater.force_update()
    diags.wait(lambda m: any(s.name.endswith('servo_3 (id 3)') for s in m.status), 5)
    updater.remove('servo_3 (id 3)')
    updater.add('servo_9 (id 9)', lambda stat: stat.summary(OK, 'fine'))
    start = len(diags)
    updater.force_update()
    msg = diags.wait(lambda m: any(s.name.endswith('servo_9 (id 9)') for s in m.status), 5,
                     start=start)
    names = [s.name for s in msg.status]
    assert names == ['/servo_bus_removal: bus', '/servo_bus_removal: servo_9 (id 9)']


def test_a_throttle_lets_one_line_per_key_and_period_through_and_counts_the_rest():
    throttle = Throttle()
    assert throttle.admit('a', 10.0, 5.0) == ''
    assert throttle.admit('a', 11.0, 5.0) is None
    assert throttle.admit('b', 11.0, 5.0) == ''  # keys apart
    assert throttle.admit('a', 14.9, 5.0) is None
    assert throttle.admit('a', 15.0, 5.0) == ' (2 more like it since the last report)'
    assert throttle.admit('a', 20.0, 5.0) == ''
