#!/usr/bin/env python3
"""Heading error of a map's odometry edges against ground truth.

Usage: bench/odometry_edges.py MAP_DIR GROUND_TRUTH.tum

MAP_DIR is a `cloi map` output folder (graph.g2o, trajectory.tum). Each graph vertex is found
in trajectory.tum by its position to get its stamp, the ground truth is read at that stamp, and
every edge i -> i+1 (the front-end's measurement between consecutive keyframes) is compared
with the true relative pose. Prints the RMS heading error, its lag-1 autocorrelation (near -0.5
when each keyframe's heading carries an independent error, near 0 for a random walk), and the
absolute heading error on straight stretches (no true rotation), which shows scan-to-scan
jitter apart from turns.
"""
import math,bisect,collections,sys
d=sys.argv[1]; gtf=sys.argv[2]
V={};E=[]
for l in open(d+'/graph.g2o'):
    p=l.split()
    if p[0]=='VERTEX_SE2': V[int(p[1])]=tuple(map(float,p[2:5]))
    if p[0]=='EDGE_SE2': E.append((int(p[1]),int(p[2]),tuple(map(float,p[3:6]))))
traj=[tuple(map(float,l.split()[:8])) for l in open(d+'/trajectory.tum') if not l.startswith('#')]
gt=[tuple(map(float,l.split()[:8])) for l in open(gtf) if not l.startswith('#')]
gts=[g[0] for g in gt]
idx=collections.defaultdict(list)
for t in traj: idx[(round(t[1],3),round(t[2],3))].append(t[0])
def stamp_of(v):
    x,y,_=V[v]; k=(round(x,3),round(y,3))
    return idx[k][0] if idx.get(k) else min(traj,key=lambda t:(t[1]-x)**2+(t[2]-y)**2)[0]
def gtpose(t):
    i=min(bisect.bisect_left(gts,t),len(gt)-1); g=gt[i]; return g[1],g[2],2*math.atan2(g[6],g[7])
def between(a,b):
    dx,dy=b[0]-a[0],b[1]-a[1]; c,s=math.cos(a[2]),math.sin(a[2])
    return (c*dx+s*dy, -s*dx+c*dy, (b[2]-a[2]+math.pi)%(2*math.pi)-math.pi)
errs=[]
for f,t,z in E:
    if t==f+1:
        g=between(gtpose(stamp_of(f)),gtpose(stamp_of(t)))
        errs.append((f,z[2]-g[2], z[0]-g[0]))
th=[e[1] for e in errs]
n=len(th); m=sum(th)/n
var=sum((x-m)**2 for x in th)/n
ac=sum((th[i]-m)*(th[i+1]-m) for i in range(n-1))/(n-1)/var
print(d,'odo edges',n,'heading err rms deg',round(math.degrees(math.sqrt(var)),3),'lag1 autocorr',round(ac,3),'x err rms',round(math.sqrt(sum(e[2]**2 for e in errs)/n),4))
# straight segments only
st=[]
for f,t,z in E:
    if t==f+1:
        a=gtpose(stamp_of(f)); b=gtpose(stamp_of(t))
        if abs(b[2]-a[2])<1e-6:
            st.append(abs(z[2]))
st.sort()
print('straight edges',len(st),'abs heading err median deg',round(math.degrees(st[len(st)//2]),3),'p90',round(math.degrees(st[9*len(st)//10]),3))
