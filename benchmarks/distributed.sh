#!/usr/bin/env bash
# The measurements of docs/distributed.md: trained stacks deployed with each layer in a process of its
# own, at several speeds, with a slow link to one layer or the other, against the simulated delayed
# setting, with a layer that dies, and with Ray actors. Usage:
#   benchmarks/distributed.sh PENDULUM_TLA_C PENDULUM_TLA_C_DELAY1 IDP_REALTIME HOPPER_REALTIME [OUT]
# (trained run directories; OUT defaults to runs/distributed). Each `layered deploy` writes its JSON
# files, deploy.md and deploy.png under OUT/<stack>/<what>/.
set -euo pipefail
pendulum=$1 delayed=$2 idp=$3 hopper=$4 out=${5:-runs/distributed}
speeds=1,2,5,10,20,50,100

layered deploy "$pendulum" --lockstep --speed $speeds --episodes 5 --out "$out/pendulum/speeds"
layered deploy "$idp" --lockstep --speed $speeds --episodes 5 --out "$out/idp/speeds"
layered deploy "$hopper" --lockstep --speed $speeds --episodes 5 --out "$out/hopper/speeds"
for layer in slow fast; do
  for link in 10ms 20ms±5ms 35ms±5ms; do
    layered deploy "$pendulum" --link-delay "$layer=$link" --episodes 5 --out "$out/pendulum/links"
  done
done
# a link slow enough that most answers land a base step late, and a stack trained with that delay
layered deploy "$pendulum" --link-delay 30ms±5ms --episodes 5 --out "$out/pendulum/clock-delay"
layered deploy "$delayed" --lockstep --speed 1 --link-delay 30ms±5ms --episodes 5 --out "$out/pendulum-delay1/clock-delay"
layered deploy "$pendulum" --fault fast:die@100 --episodes 5 --out "$out/pendulum/fault"
layered deploy "$pendulum" --lockstep --speed 1 --episodes 2 --transport ray --out "$out/pendulum/ray"
