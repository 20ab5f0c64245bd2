#!/usr/bin/env bash
# Test credentials for a TLS (and mutual TLS) Impulse bus with passwords: one certificate authority, a
# certificate and password for the routers, and per role a client certificate and a password. A certificate's
# common name and a password's user are the role, which the router's access control matches (see bus/router.py).
# For tests and trials only: the keys are unencrypted. The CA's private key is deleted once everything is signed,
# so a copied directory cannot sign more; run the script again for new credentials.
#
# Usage: deploy/cluster/security/make-test-certs.sh DIR [ROUTER_HOST ...]
#   The roles are those `impulse router --roles` lists, so run it where Impulse is installed (its virtualenv
#   active), or say how to run Impulse in IMPULSE, e.g. IMPULSE=".venv/bin/python -m impulse.deploy.cli".
#   DIR           where to write ca.pem, router.pem/.key/.password, users.txt and <role>.pem/.key/.password
#                 (created)
#   ROUTER_HOST   further names and addresses a router is reached by (localhost and 127.0.0.1 are always
#                 included); clients check the router's certificate against the host in their connect endpoint
set -euo pipefail

if [[ $# -lt 1 ]]; then
    echo "usage: $0 DIR [ROUTER_HOST ...]" >&2
    exit 2
fi
dir=$1
shift
hosts=(localhost 127.0.0.1)
for host in "$@"; do
    [[ " ${hosts[*]} " == *" $host "* ]] || hosts+=("$host")
done
read -r -a impulse <<< "${IMPULSE:-impulse}"
if ! role_list=$("${impulse[@]}" router --roles) || [[ -z $role_list ]]; then
    echo "$0: '${impulse[*]} router --roles' did not list the roles: activate Impulse's virtualenv or set IMPULSE" >&2
    exit 2
fi
mapfile -t roles <<< "$role_list"
days=365
mkdir -p "$dir"
# Only this user may list or read the directory: it holds every role's private keys and passwords.
chmod 700 "$dir"
cd "$dir"

# The certificate authority every party trusts.
openssl req -x509 -newkey rsa:2048 -nodes -days "$days" -subj "/CN=impulse-test-ca" \
    -keyout ca.key -out ca.pem 2>/dev/null

sign() {  # sign NAME EXTENSIONS: NAME.key + NAME.csr -> NAME.pem, signed by the CA
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$days" \
        -extfile <(printf '%s\n' "$2") -out "$1.pem" 2>/dev/null
    rm -f "$1.csr"
}

# The router: its subject alternative names are what clients verify.
san=""
for host in "${hosts[@]}"; do
    if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then san+="IP:$host,"; else san+="DNS:$host,"; fi
done
openssl req -newkey rsa:2048 -nodes -subj "/CN=router" -keyout router.key -out router.csr 2>/dev/null
sign router "subjectAltName=${san%,}
extendedKeyUsage=serverAuth,clientAuth"

# One client certificate and one password per role, the certificate's common name and the user name the role;
# users.txt is the routers' dictionary of them. The routers' own password is what one presents to another.
: > users.txt
for role in "${roles[@]}"; do
    openssl req -newkey rsa:2048 -nodes -subj "/CN=$role" -keyout "$role.key" -out "$role.csr" 2>/dev/null
    sign "$role" "extendedKeyUsage=clientAuth
subjectAltName=DNS:$role"
done
for role in router "${roles[@]}"; do
    openssl rand -hex 16 > "$role.password"
    echo "$role:$(cat "$role.password")" >> users.txt
done
rm -f ca.srl ca.key
chmod 600 ./*.key ./*.password users.txt
echo "wrote ca.pem, router.pem/.key/.password, users.txt and, for ${roles[*]}: .pem/.key/.password, to $dir" \
     "(router reached as: ${hosts[*]}; the CA's key is deleted)"
