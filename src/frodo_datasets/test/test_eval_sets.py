"""Real-capture evaluation/tuning sets: disjoint, big enough, held-out families only where they belong; pooling."""
from dataclasses import asdict

import numpy as np

from frodo_datasets.eval_sets import SETS, VARIANTS, family_table, pool, scene_config, table
from frodo_datasets.scene import compose_scene
from frodo_datasets.shapes import eval_families, extra_families, families


def _families(eval_set):
    out = []
    for _, seed, n in eval_set.scenes():
        config = scene_config(eval_set, seed, n, 'full')
        scene = compose_scene(config.objects, config.classes, seed=config.seed, family_set=config.family_set)
        out += [(o.class_name, o.family) for o in scene.objects]
    return out


def test_sets_are_disjoint_and_big_enough():
    held, tune, tune2, tune3 = (SETS[n] for n in ('realcapture', 'realcapture-tune', 'realcapture-tune2',
                                                  'realcapture-tune3'))
    seeds = [s.seeds for s in SETS.values()]   # every set, the inside-out walks (test_realwalk.py) included
    assert len(set().union(*seeds)) == sum(len(s) for s in seeds)
    assert len(held.seeds) >= 12 and sum(held.objects) >= 40
    assert sum(tune.objects) + sum(tune2.objects) >= 60
    held_families = _families(held)
    unseen = [f for c, f in held_families if f in eval_families(c)]
    assert len(unseen) >= 8 and {c for c, f in held_families if f in eval_families(c)} == {'chair', 'dining table'}
    assert not any(f in eval_families(c) for c, f in _families(tune) + _families(tune2) + _families(tune3)
                   + _families(SETS['realwalk-tune']) + _families(SETS['realwalk-tune2'])
                   + _families(SETS['realwalk-tune3']))
    assert all(f in eval_families(c) for c, f in _families(SETS['realwalk']))   # designs no prior trained on
    # the third tuning set: designs the first prior `furniture` has not seen, of both classes, next to training
    # designs
    third = _families(tune3)
    assert {c for c, f in third if f in extra_families(c)} == {'chair', 'dining table'}
    assert sum(f in extra_families(c) for c, f in third) >= 15 and any(f in families(c) for c, f in third)


def test_variants_change_one_condition_at_a_time():
    held = SETS['realcapture']
    configs = {v: asdict(scene_config(held, 9100, 3, v)) for v in VARIANTS}
    assert configs['full']['scene'] == 'handheld' and configs['full']['frames'] == 35
    assert configs['full100']['frames'] == 100
    full, big = configs['full'], configs['full640']
    assert (big['width'], big['height']) == (640, 480) and (full['width'], full['height']) == (320, 240)
    assert {k for k in full if big[k] != full[k]} == {'width', 'height', 'mask_noise'}
    assert {k for k in full['mask_noise'] if big['mask_noise'][k] != full['mask_noise'][k]} == \
        {'morph_px', 'boundary_px', 'bleed_px'}
    assert big['mask_noise']['bleed_px'] == 2 * full['mask_noise']['bleed_px']
    assert {k for k in full if configs['depth'][k] != full[k]} == {'depth'} and configs['depth']['depth']
    walk = SETS['realwalk-tune']
    assert scene_config(walk, walk.seeds[0], 4, 'full640').scene == scene_config(walk, walk.seeds[0], 4, 'full').scene
    plain = configs['plain']
    changed = {v: {k for k in plain if configs[v][k] != plain[k]}
               for v in ('occlusion', 'masks', 'drift', 'landmarks', 'camera')}
    assert changed == {'occlusion': {'tuck_chairs', 'clutter'}, 'masks': {'mask_noise'}, 'drift': {'pose_noise'},
                       'landmarks': {'slam_texture_min', 'slam_density', 'slam_noise_m'},
                       'camera': {'realism', 'capture'}}
    assert {k for k in plain if configs['truncation'][k] != configs['keyframes'][k]} == {'frames'}


def test_pool_and_table(tmp_path):
    def report(pairs, n_gt, fp):
        return {'pairs': [{'f1': f, 'comp': f + 5, 'cd_cm': c, 'centroid_distance_m': d, 'gt_id': i + 1}
                          for i, (f, c, d) in enumerate(pairs)],
                'overall': {'n_gt': n_gt, 'false_positives': fp}}
    reports = [report([(80.0, 3.0, 0.05), (60.0, 5.0, 0.15)], 3, 1), report([(90.0, 2.0, 0.10)], 1, 0)]
    s = pool(reports)
    assert s['recall'] == 75.0 and s['fp_per_scene'] == 0.5 and s['found'] == 3
    assert np.isclose(s['median_centre_cm'], 10.0) and np.isclose(s['mean_cd_cm'], 10 / 3)
    assert np.isclose(s['mean_f1'], 230 / 3) and np.isclose(s['mean_f1_all'], 230 / 4)
    assert np.isclose(s['mean_comp'], 245 / 3)
    import json
    (tmp_path / 'results' / 'full').mkdir(parents=True)
    for i, r in enumerate(reports):
        (tmp_path / 'results' / 'full' / f'realcapture-{9100 + i}.json').write_text(json.dumps(r))
    text = table(SETS['realcapture'], tmp_path, ['full', 'plain'], markdown=True)
    assert '| full | 2 | 0 | 4 | 75.0 | 0.50 | 10.0 | 3.33 | 76.7 | 57.5 |' in text and 'plain' not in text
    rows = [line.split('|') for line in family_table(SETS['realcapture'], tmp_path, 'full').splitlines()[2:]]
    assert sum(int(r[3]) for r in rows) == 3 + 4  # every object of the two rooms, split by class and family kind
