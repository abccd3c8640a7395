#!/usr/bin/env python3
"""variant.py SRC DST key=json ... : a copy of a bundle with sampler fields changed, manifest re-hashed."""
import json, hashlib, shutil, os, sys
src, dst = sys.argv[1], sys.argv[2]
if os.path.exists(dst): shutil.rmtree(dst)
shutil.copytree(src, dst)
b = json.load(open(dst + '/bundle.json'))
for kv in sys.argv[3:]:
    k, v = kv.split('=', 1)
    b['sampler'][k] = json.loads(v)
b['name'] = os.path.basename(dst)
json.dump(b, open(dst + '/bundle.json', 'w'), indent=2)
m = json.load(open(dst + '/manifest.json'))
for f in m['files']:
    m['files'][f] = hashlib.sha256(open(dst + '/' + f, 'rb').read()).hexdigest()
json.dump(m, open(dst + '/manifest.json', 'w'), indent=2)
print(dst, b['sampler'])
