"""Failures of clutter attempts by the object the judge names, over trial folders."""
import collections, re, sys
from drake_grasp.evaluation.records import load_records
dirs = sys.argv[1:]
fail = collections.Counter(); att = collections.Counter(); cls = collections.Counter()
for d in dirs:
    for t in (r.to_dict() for r in load_records(d)):
        if t['failure_class'] == 'simulation-error':
            continue
        obj = t.get('grasped_object_id')
        if not obj and t['failure_reason']:
            m = re.search(r'([a-z_]+_\d{3})', t['failure_reason']); obj = m.group(1) if m else None
        cat = obj.rsplit('_', 1)[0] if obj else 'none named'
        att[cat] += 1
        if not t['success']:
            fail[cat] += 1; cls[(cat, t['failure_class'])] += 1
tot = sum(att.values()); nf = sum(fail.values())
print(f"{tot} attempts, {nf} failed")
for cat, n in fail.most_common():
    print(f"  {cat:12s} failed {n:3d} of {att[cat]:3d} attempts;",
          {c: k for (cc, c), k in cls.items() if cc == cat})
