import time, sys, cv2, numpy as np
from pipeline.synthetic.large import render_large, true_pairs
from pipeline.synthetic.large_layouts import LargeSceneConfig
from pipeline.frontend.features import extract_sift
from pipeline.frontend.retrieval import retrieve_pairs, pair_recall
lay, n, w = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
t=time.time()
s = render_large(LargeSceneConfig(layout=lay, n_views=n, width=w, height=w*3//4, focal=560*w/640, points_per_view=1500), None, seed=0)
t1=time.time()
kps=[extract_sift(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in s["images"]]
t2=time.time()
tp = true_pairs(s["overlap"], 0.1)
print(lay, n, w, "render", round(t1-t,2), "sift", round(t2-t1,2), "true", len(tp), len(tp)/(n*(n-1)/2), "median kp", np.median([len(k.descriptors) for k in kps]))
for br in [None]:
  for k in (5,6,7,8,None):
    r = retrieve_pairs([k_.descriptors for k_ in kps], k, responses=[k_.responses for k_ in kps], branching=br)
    print(br, k, {a:round(b,3) for a,b in pair_recall(r["pairs"], tp, n).items()}, round(r["time_s"],2), r["n_words"])
