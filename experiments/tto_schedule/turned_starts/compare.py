"""Per-seed comparison of a variant's rows (JSON lines) with the default path's validation sweep
(``baseline_sweep.jsonl``, 60a693c's code, session 42): carotid mPCD (views averaged, mm), rotation error (deg),
the start chosen. Usage: python3 experiments/tto_schedule/turned_starts/compare.py VARIANT.jsonl
"""
import json, sys, numpy as np
sw={r['seed']:r for r in map(json.loads,open(__file__.replace('compare.py', 'baseline_sweep.jsonl')))}
rows=[json.loads(l) for l in open(sys.argv[1])]
a=[];b=[];ra=[];rb=[];ta=[];tb=[]
for r in rows:
    s=sw[r['seed']]; f=r['final']; g=s['final']
    ma=(g['pa'][0]+g['lat'][0])/2; mb=(f['pa'][0]+f['lat'][0])/2
    a.append(ma); b.append(mb); ra.append(g['pa'][1]); rb.append(f['pa'][1]); ta.append(s['total_s']); tb.append(r['total_s'])
    flag = '' if abs(ma-mb)<0.3 else ('BETTER' if mb<ma else 'WORSE')
    print(r['seed'], f"{ma:5.2f} {g['pa'][1]:5.2f} {s['chosen'][:8]:8s} -> {mb:5.2f} {f['pa'][1]:5.2f} {r['chosen'][:8]:8s} turn {r.get('turn')} gain {r.get('gain',0):.3f} scan {r.get('scan_s',0):.2f}s {s['total_s']}->{r['total_s']} {flag}")
a,b=np.array(a),np.array(b)
print(f"n {len(a)} mPCD {a.mean():.3f} -> {b.mean():.3f}; median {np.median(a):.3f} -> {np.median(b):.3f}; rot {np.mean(ra):.2f} -> {np.mean(rb):.2f}; >5mm views? time {np.mean(ta):.1f} -> {np.mean(tb):.1f}")
