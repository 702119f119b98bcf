#!/usr/bin/env bash
# Make a site's certificates for router-tls-acl.json5 with openssl (docs/deploy.md).
#
#   deploy/make-certs.sh DIR NAME...
#
# Creates DIR/ca.{key,pem} (the site's certificate authority) unless it exists, then for
# each NAME a key DIR/NAME.key and a certificate DIR/NAME.pem signed by that CA, with
# common name NAME. Client NAMEs are process ids (radar2d, fuser, trk-angle, ...): the
# router grants rights by common name. The NAME "router" gets the subject alternative
# names in ZF_ROUTER_SAN (default DNS:localhost,IP:127.0.0.1), which must name the host
# that clients dial, e.g. ZF_ROUTER_SAN=DNS:fusion-centre.example.org,IP:10.0.0.1.
#
# Keys are written without a passphrase (services start unattended) and readable by
# their owner only: keep DIR/ca.key off the hosts, and give each host only its own keys.
set -euo pipefail

if [[ $# -lt 2 ]]; then
    echo "usage: $0 DIR NAME..." >&2
    exit 2
fi
dir=$1
shift
for name in "$@"; do
    if [[ ! $name =~ ^[A-Za-z0-9_.+-]{1,64}$ ]]; then
        echo "$0: $name: a name is a zfusion process id, [A-Za-z0-9_.+-]{1,64}" >&2
        exit 2
    fi
done
days=${ZF_CERT_DAYS:-365}
curve=(-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -noenc)
mkdir -p "$dir"
umask 077

quiet() {  # openssl chatters on stderr even when all is well: show it only on failure
    local out
    if ! out=$("$@" 2>&1); then
        echo "$out" >&2
        return 1
    fi
}

if [[ ! -f $dir/ca.pem ]]; then
    quiet openssl req -x509 "${curve[@]}" -days "$days" -keyout "$dir/ca.key" -out "$dir/ca.pem" \
        -subj "/CN=zfusion site CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

for name in "$@"; do
    ext=(-addext "basicConstraints=critical,CA:FALSE" -addext "extendedKeyUsage=serverAuth,clientAuth")
    if [[ $name == router ]]; then
        ext+=(-addext "subjectAltName=${ZF_ROUTER_SAN:-DNS:localhost,IP:127.0.0.1}")
    fi
    quiet openssl req -x509 "${curve[@]}" -days "$days" -keyout "$dir/$name.key" -out "$dir/$name.pem" \
        -subj "/CN=$name" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" "${ext[@]}"
done
chmod 644 "$dir"/*.pem  # certificates are public; keys stay private
