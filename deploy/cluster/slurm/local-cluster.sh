#!/bin/bash
# A three-node SLURM cluster on one Linux machine, for trying deploy/cluster/slurm/impulse.sbatch without a real cluster.
#
#   sudo deploy/cluster/slurm/local-cluster.sh up      # prints the SLURM_CONF to export
#   export SLURM_CONF=/tmp/impulse-slurm/slurm.conf
#   IMPULSE_GPUS_PER_NODE=2 IMPULSE_ACTOR_CPUS=1 IMPULSE_HEAD_CPUS=2 \
#       IMPULSE_OVERRIDES="ppo.num_envs=32 ppo.num_steps=32 ppo.num_minibatches=2 total_env_steps=81920" \
#       sbatch --ntasks-per-node=2 --cpus-per-task=1 --gpus-per-node=2 --time=30 deploy/cluster/slurm/impulse.sbatch
#   sudo deploy/cluster/slurm/local-cluster.sh down
#
# Each node is a network namespace of its own (imp-node1..3, addresses 10.88.0.1..3 on a bridge whose host side,
# 10.88.0.254, is the controller imp-ctl), with its own host name (a UTS namespace) and one slurmd. The nodes share
# this machine's filesystem, so the repository, its .venv and the run directory are "on a shared filesystem" as
# the template expects. Each node declares 8 CPUs and two GPUs; the GPUs are character devices that behave like
# /dev/null, enough for SLURM to schedule them and set CUDA_VISIBLE_DEVICES; Impulse then runs on the CPU. Jobs run
# as the user who submits them (root here), under SLURM 22.05 from Debian 12 (`apt-get install slurmctld slurmd
# slurm-client munge`); no cgroup constraints, no accounting.
#
# What it shows: that the template's allocation, job steps, credentials, router endpoint, supervision and shutdown
# work under a real slurmctld and real slurmds with separate network stacks. What it cannot show: real GPUs, a real
# network, a shared filesystem that is not local, or a site's own SLURM configuration.
set -euo pipefail

DIR=${IMPULSE_SLURM_DIR:-/tmp/impulse-slurm}
NODES=(imp-node1 imp-node2 imp-node3)
CONTROLLER=imp-ctl
BRIDGE=impslurm0
SUBNET=10.88.0
HOSTS_MARK="# impulse local SLURM cluster"

need() {
    command -v "$1" >/dev/null || { echo "local-cluster.sh: $1 not found ($2)" >&2; exit 2; }
}

hosts_lines() {
    echo "$SUBNET.254 $CONTROLLER $HOSTS_MARK"
    for i in "${!NODES[@]}"; do echo "$SUBNET.$((i + 1)) ${NODES[$i]} $HOSTS_MARK"; done
}

up() {
    [[ $(id -u) == 0 ]] || { echo "local-cluster.sh: needs root (namespaces, daemons)" >&2; exit 2; }
    need ip "iproute2"
    need slurmctld "apt-get install slurmctld slurmd slurm-client munge"
    need slurmd "apt-get install slurmd"
    need munged "apt-get install munge"
    mkdir -p "$DIR"/{state,spool,log,gpu}
    for g in 0 1; do [[ -e $DIR/gpu/nvidia$g ]] || mknod "$DIR/gpu/nvidia$g" c 1 3; done

    # The network: a bridge on the host, one namespace per node plugged into it.
    ip link add "$BRIDGE" type bridge
    ip addr add "$SUBNET.254/24" dev "$BRIDGE"
    ip link set "$BRIDGE" up
    for i in "${!NODES[@]}"; do
        node=${NODES[$i]}
        ip netns add "$node"
        ip link add "v$node" type veth peer name eth0 netns "$node"
        ip link set "v$node" master "$BRIDGE" up
        ip -n "$node" addr add "$SUBNET.$((i + 1))/24" dev eth0
        ip -n "$node" link set eth0 up
        ip -n "$node" link set lo up
        mkdir -p "/etc/netns/$node"
        { echo "127.0.0.1 localhost"; hosts_lines; } > "/etc/netns/$node/hosts"
    done
    grep -q "$HOSTS_MARK" /etc/hosts || hosts_lines >> /etc/hosts

    # SLURM's configuration, in DIR (SLURM_CONF points every command and daemon there).
    {
        echo "ClusterName=impulse-local"
        echo "SlurmctldHost=$CONTROLLER($SUBNET.254)"
        echo "SlurmUser=root"
        echo "AuthType=auth/munge"
        echo "CredType=cred/munge"
        echo "ProctrackType=proctrack/linuxproc"   # every process a task starts belongs to its step
        echo "TaskPlugin=task/none"
        echo "SelectType=select/cons_tres"
        echo "SelectTypeParameters=CR_Core"
        echo "GresTypes=gpu"
        echo "SlurmdParameters=config_overrides"     # believe the CPU counts below, not the hardware
        echo "StateSaveLocation=$DIR/state"
        echo "SlurmdSpoolDir=$DIR/spool/%n"
        echo "SlurmctldPidFile=$DIR/slurmctld.pid"
        echo "SlurmdPidFile=$DIR/slurmd-%n.pid"
        echo "SlurmctldLogFile=$DIR/log/slurmctld.log"
        echo "SlurmdLogFile=$DIR/log/slurmd-%n.log"
        echo "ReturnToService=2"
        echo "KillWait=30"
        for i in "${!NODES[@]}"; do
            echo "NodeName=${NODES[$i]} NodeAddr=$SUBNET.$((i + 1)) CPUs=8 RealMemory=4000 Gres=gpu:2 State=UNKNOWN"
        done
        echo "PartitionName=main Nodes=$(IFS=,; echo "${NODES[*]}") Default=YES MaxTime=INFINITE State=UP"
    } > "$DIR/slurm.conf"
    echo "Name=gpu File=$DIR/gpu/nvidia[0-1]" > "$DIR/gres.conf"
    printf 'CgroupPlugin=cgroup/v1\nCgroupAutomount=no\n' > "$DIR/cgroup.conf"
    export SLURM_CONF=$DIR/slurm.conf

    # The daemons: munge (authentication), the controller on the host side, one slurmd per node.
    pgrep -x munged >/dev/null || runuser -u munge -- munged
    unshare --uts sh -c "hostname $CONTROLLER; exec slurmctld -D" >"$DIR/log/slurmctld.out" 2>&1 &
    echo $! > "$DIR/daemons.pid"
    sleep 2
    for node in "${NODES[@]}"; do
        ip netns exec "$node" unshare --uts sh -c "hostname $node; exec slurmd -D" >"$DIR/log/$node.out" 2>&1 &
        echo $! >> "$DIR/daemons.pid"
    done
    for _ in $(seq 30); do
        if [[ $(sinfo --noheader --states=idle --format=%D 2>/dev/null) == "${#NODES[@]}" ]]; then
            sinfo --Node --format="%N %T %c %G"
            echo "ready: export SLURM_CONF=$SLURM_CONF"
            return 0
        fi
        sleep 1
    done
    echo "local-cluster.sh: the nodes did not come up; see $DIR/log" >&2
    exit 1
}

down() {
    if [[ -f $DIR/daemons.pid ]]; then
        xargs kill < "$DIR/daemons.pid" 2>/dev/null || true
        rm -f "$DIR/daemons.pid"
        sleep 2
    fi
    for node in "${NODES[@]}"; do
        ip netns del "$node" 2>/dev/null || true
        rm -rf "/etc/netns/$node"
    done
    ip link del "$BRIDGE" 2>/dev/null || true
    sed -i "/$HOSTS_MARK/d" /etc/hosts
    echo "stopped; $DIR keeps the logs and SLURM's state"
}

case ${1:-} in
    up) up ;;
    down) down ;;
    *) echo "usage: $0 up|down   (IMPULSE_SLURM_DIR, default /tmp/impulse-slurm, holds config, state and logs)" >&2
       exit 2 ;;
esac
