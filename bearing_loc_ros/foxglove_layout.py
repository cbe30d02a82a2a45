"""The shipped Foxglove layout (config/foxglove_layout.json).

Panels: a Map (the ``/map_geojson`` picture and ``/fix/navsat``), a 3D panel (``/markers``
and ``/accuracy_map`` in the ``map`` frame) and a Plot of the fix σ (horizontal and 3D, m)
and the fix rate (Hz, right axis) from ``/view/fix_stats``.

The panel configurations are built with foxglove-sdk's ``foxglove.layouts`` (so their keys
follow the SDK's schema) and written in the classic layout file format that both Foxglove
and Lichtblick import ("Import from file"): ``configById`` (panel id ``<type>!<id>`` ->
config), ``layout`` (a tree of ``first``/``second``/``direction``/``splitPercentage``),
``globalVariables``, ``userNodes``, ``playbackConfig``.

Regenerate after a change:
``python -m bearing_loc_ros.foxglove_layout config/foxglove_layout.json``.
"""

import json
import sys

from .foxglove_view import GEOJSON_TOPIC, STATS_TOPIC


def panels():
    """(classic panel id, foxglove.layouts panel) of the Map, 3D and Plot panels."""
    import foxglove.layouts as fl
    map_panel = fl.MapPanel(title='Map', config=fl.MapConfig(
        layer='map', follow_topic='/fix/navsat', zoom_level=9,
        topic_colors={GEOJSON_TOPIC: '#1f77b4', '/fix/navsat': '#2ca02c'}))
    scene = fl.ThreeDeePanel(title='3D', config=fl.ThreeDeeConfig(
        follow_tf='map', follow_mode='follow-none',
        camera_state=fl.ThreeDeeCameraState(distance=150000.0, perspective=True, phi=40.0,
                                            target_offset=(0.0, 0.0, 0.0), theta_offset=0.0,
                                            fovy=45.0, near=1.0, far=1.0e7),
        topics={'/markers': fl.BaseRendererRosMarkerTopicSettings(visible=True),
                '/accuracy_map': fl.BaseRendererRosOccupancyGridTopicSettings(
                    visible=True, color_mode='map', alpha=0.6, frame_locked=True)}))
    plot = fl.PlotPanel(title='Fix sigma and rate', config=fl.PlotConfig(
        paths=[fl.PlotSeries(value=f'{STATS_TOPIC}.sigma_horizontal_m',
                             label='sigma horizontal (m)', timestamp_method='receiveTime'),
               fl.PlotSeries(value=f'{STATS_TOPIC}.sigma_3d_m', label='sigma 3D (m)',
                             timestamp_method='receiveTime'),
               fl.PlotSeries(value=f'{STATS_TOPIC}.fix_rate_hz', label='fix rate (Hz)',
                             timestamp_method='receiveTime', use_right_y_axis=True)],
        show_legend=True, legend_display='floating', x_axis_val='timestamp',
        y_axis_label='sigma (m)'))
    return [('map!bearingloc', map_panel), ('3D!bearingloc', scene),
            ('Plot!bearingloc', plot)]


def layout():
    """The layout as a dict in the classic layout file format (module docstring)."""
    config = {}
    for pid, panel in panels():
        cfg = json.loads(panel.config.to_json())
        cfg['title'] = panel.title
        config[pid] = cfg
    ids = [pid for pid, _ in panels()]
    return {'configById': config, 'globalVariables': {}, 'userNodes': {},
            'linkedGlobalVariables': [],
            'playbackConfig': {'speed': 1, 'messageOrder': 'receiveTime'},
            'layout': {'direction': 'row', 'first': ids[0], 'splitPercentage': 50,
                       'second': {'direction': 'column', 'first': ids[1], 'second': ids[2],
                                  'splitPercentage': 65}}}


def layout_json():
    """The layout file's text (indented JSON, trailing newline)."""
    return json.dumps(layout(), indent=2, sort_keys=True) + '\n'


def main(argv=None):
    """Write the layout to the path given (default: stdout)."""
    argv = sys.argv[1:] if argv is None else argv
    text = layout_json()
    if argv:
        with open(argv[0], 'w', encoding='utf-8') as f:
            f.write(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
