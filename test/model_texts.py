"""
Hostile model texts: the seeded corpus of the model-text fuzz test and benchmark.

:func:`corpus` draws texts from generators of the kinds of input issue #16 reported or that an
attacker on the ROS graph would try: long products, nested powers, many or malformed
``exp(...)`` factors, huge numbers, deep nesting, Unicode, keywords, dunder names, attribute
access, random token soup built from the grammar's tokens, random expressions of the grammar,
texts at the size limits, equations. The same seed gives the same texts, so a failure can be
replayed with :func:`corpus` alone. :data:`ISSUE_EXAMPLES` are the issue's own texts.
"""

import keyword
import random
from typing import Callable, List, Optional, Tuple

__all__ = ['CONTROLLER_PLANT', 'GENERATORS', 'ISSUE_EXAMPLES', 'corpus']

# (plant text, controller text or None) of issue #16.
ISSUE_EXAMPLES: List[Tuple[str, Optional[str]]] = [
    ('K/(' + '*'.join(f'a{i}' for i in range(60)) + ')', None),
    ('K/(' + '*'.join(f'a{i}' for i in range(100)) + ')', None),
    ('exp((a+b+c+d+e)**10)/(s+1)', None),
    ('*'.join(['exp((a+b+c+d+e)**10)'] * 3) + '/(s+1)', None),
    ('K*exp(-tau*s)/(T*s + 1)', "__import__('os')"),
    ('K*exp(tau*s)/(T*s + 1)', None),
    ('K*exp(-tau*s)**-1/(s+1)', None),
    ('K*exp(-tau*s)**2/(s+1)', None),
    ('exp(-tau*s)', None),
    ('1/(m*s**2 + d*s + k)', 's**3'),
    ('1/(m*s**2 + d*s + k)', 's'),
]
# The plant that corpus texts are tried as controllers of.
CONTROLLER_PLANT = '1/(m*s**2 + d*s + k)'

_NAMES = ['K', 'T', 'tau', 'a', 'b', 'c', 'm', 'd', 'k', 'w', 'z', 'T1', 'T2', 'b0', 'a0', 'a1']
_NUMBERS = ['0', '1', '2', '3', '0.5', '.5', '1.', '2.5e-3', '1e3', '1e300', '1e-300', '1e400',
            '1e-400', '9' * 31, '9' * 40, '0.0', '1e999999999', '0e999999', '17', '33', '1.5']
_TOKENS = (['s', 'pi', 'exp', '(', ')', '+', '-', '*', '/', '**', '^', '=', ' '] + _NAMES[:6]
           + _NUMBERS[:8])
_UNICODE = ['\u00b2', '\u00a0', '\u0661', '\uff08', '\u2212', '\u00d7', '\u03c4', '\u200b',
            '\u202e', '\U0001f600', '\u0301', '\ufeff', '\x00', '\u2028', 'K\u0131', '\u212a']
_INJECTIONS = [
    "__import__('os').system('true')", '().__class__.__bases__[0].__subclasses__()',
    's.__class__', 'K.real/(s+1)', '__builtins__', 'K/(s+__dict__)', 'eval("1")',
    'exec(K)', 'open(K)', 'getattr(K, s)', 'lambda: 1', 'K if s else T', '[K]', '{K}', 'K[0]',
    'K;import os', 'K/(s+1) # comment', 'f"{K}"', 'K @ s', 'K % s', 'K // s', 'K, s', '`s`',
    'K\\\n/(s+1)', "'K'/(s+1)", 'K/(s+1)\n\n', '\tK/(s+1)\r', 'K := 1', 'K/(s+1) and T',
    'not K', 'K is s', 'K == s', 'K != s', 'K < s', '~K', 'K | s', 'K & s', 'K << 2', '!K',
    '$K', 'K?', 'K.__init__.__globals__', 'sympy.exp(s)', 'np.exp(-tau*s)', 'Symbol("x")',
    'K/(s+1)' + ')' * 5, '(' * 5 + 'K/(s+1)', '',
]


def _number(rng: random.Random) -> str:
    return rng.choice(_NUMBERS) if rng.random() < 0.5 else str(rng.randint(0, 20))


def _name(rng: random.Random) -> str:
    return rng.choice(_NAMES)


def _expression(rng: random.Random, depth: int, dead_time: bool = True) -> str:
    """Return a random text of the grammar (valid syntax, any meaning)."""
    if depth <= 0:
        return rng.choice([_name(rng), _name(rng), 's', 's', _number(rng), 'pi'])
    choice = rng.random()
    if choice < 0.35:
        operator = rng.choice(['+', '-', '*', '/', '*', '/'])
        return (f'{_expression(rng, depth - 1, dead_time)}{operator}'
                f'{_expression(rng, depth - 1, dead_time)}')
    if choice < 0.55:
        return f'({_expression(rng, depth - 1, dead_time)})'
    if choice < 0.7:
        exponent = rng.choice(['2', '3', '-1', '-2', '0.5', '1.5', '16', '33', '-0.5', 'K',
                               '(1/3)', '0', '(-1)', str(rng.randint(-40, 40))])
        return f'({_expression(rng, depth - 1, dead_time)})**{exponent}'
    if choice < 0.8:
        return f'-{_expression(rng, depth - 1, dead_time)}'
    if choice < 0.9 and dead_time:
        return rng.choice([
            f'exp(-{_name(rng)}*s)', f'exp({_expression(rng, depth - 1, False)})',
            f'exp(-({_expression(rng, depth - 1, False)})*s)', f'exp({_name(rng)}*s)',
            f'exp(-{_number(rng)}*s)'])
    return _expression(rng, 0, dead_time)


def _plausible(rng: random.Random) -> str:
    """Return a gain, an optional dead time and a rational N/D like real grey-box models."""
    def polynomial(degree: int, monic: bool) -> str:
        terms = [f'{_name(rng)}*s**{power}' for power in range(degree, 0, -1)]
        terms.append(_name(rng) if rng.random() < 0.8 else _number(rng))
        if monic and terms:
            terms[0] = f's**{degree}'
        return ' + '.join(terms)
    kind = rng.random()
    if kind < 0.3:
        den = polynomial(rng.randint(1, 12), rng.random() < 0.5)
        num = polynomial(rng.randint(0, 3), False)
        text = f'({num})/({den})'
    elif kind < 0.6:
        factors = [rng.choice([f'({_name(rng)}*s + 1)', f'(s + {_name(rng)})',
                               f'({_name(rng)}**2*s**2 + 2*{_name(rng)}*{_name(rng)}*s + 1)'])
                   for _ in range(rng.randint(1, 5))]
        text = f'{_name(rng)}/(' + '*'.join(factors) + ')'
    elif kind < 0.8:
        power = rng.randint(1, 20)
        text = f'{_name(rng)}/({_name(rng)}*s + {_name(rng)})**{power}'
    else:
        text = f'{_name(rng)}*({_name(rng)}/{_name(rng)})**0.5/(s**2 + {_name(rng)}*s + 1)'
    if rng.random() < 0.4:
        text = rng.choice(['exp(-tau*s)*', 'exp(-(tau + L)*s)*', 'exp(-0.1*s)*',
                           'exp(-tau**2*s)*', 'exp(-tau*s/2)*']) + text
    return text


def _product(rng: random.Random) -> str:
    names = '*'.join(f'a{i}' for i in range(rng.randint(2, 120)))
    return rng.choice([f'K/({names})', f'K/(({names})*s + 1)', f'({names})/(s + 1)',
                       f'K*exp(-({names})*s)/(s + 1)'])


def _lags(rng: random.Random) -> str:
    count = rng.randint(2, 12)
    factor = rng.choice(['(T{i}*s + 1)', '(T{i}**2*s**2 + 2*z{i}*T{i}*s + 1)', '(s + p{i})'])
    return 'K/(' + '*'.join(factor.format(i=i) for i in range(count)) + ')'


def _dense(rng: random.Random) -> str:
    names = '+'.join(rng.sample(_NAMES, rng.randint(2, 12)))
    return rng.choice([f'K/({names} + s)**{rng.randint(1, 12)}',
                       f'K/(({names})*s + 1)**{rng.randint(1, 33)}',
                       f'({names})**{rng.randint(1, 20)}/(s + 1)**{rng.randint(1, 20)}'])


def _black_box(rng: random.Random) -> str:
    degree = rng.randint(1, 40)
    num = ' + '.join(f'b{i}*s**{i}' for i in range(rng.randint(1, degree)))
    den = f's**{degree} + ' + ' + '.join(f'a{i}*s**{i}' for i in range(degree))
    return f'({num})/({den})'


def _nested_power(rng: random.Random) -> str:
    text = rng.choice(['9', '2', 's', '(s+1)', '(a+b+s)', 'K', '(2*pi)', '(a/b)', '(-1)'])
    for _ in range(rng.randint(1, 8)):
        text = f'({text})**{rng.choice(["2", "16", "-16", "0.5", "33", "10", "-1", "1.5"])}'
    return rng.choice([f'K*{text}/(s+1)', f'K/{text}', f'{text}', f'K/(s+{text})'])


def _exponentials(rng: random.Random) -> str:
    argument = rng.choice(['-tau*s', 'tau*s', '-s', 's', '-tau*s**2', '-tau/s', '-tau*s + 1',
                           'a', '(a+b+c+d+e)**10', '-(a-b)*s', '-(tau1 + tau2)*s', '0*s',
                           '-0.1*s', '0.1*s', '-(a+b+c+d+e)**10*s', '-tau*s*s/s', '-K*T*s',
                           'exp(-tau*s)', '-1e300*s', '-1e-300*s', '-pi*s', '-(3 - pi)*s'])
    factor = f'exp({argument})'
    count = rng.randint(1, 4)
    shape = rng.choice(['K*{f}/(T*s + 1)', '{f}', 'K*{f}', '1/({f}*(s + 1))', '{f}**2/(s+1)',
                        '{f}**-1/(s + 1)', 'K/(s + 1) + {f}', '{f}/(s + 1) - K/(s + 2)',
                        '(K*{f})/(T*s + 1)', '-{f}/(T*s + 1)', 'K/(s+1)*({f})**1',
                        '2**{f}/(s+1)', 's**{f}/(s+1)'])
    return shape.format(f='*'.join([factor] * count))


def _nesting(rng: random.Random) -> str:
    depth = rng.randint(30, 300)
    return rng.choice(['(' * depth + 'K' + ')' * depth + '/(s+1)', '-' * depth + 'K/(s+1)',
                       'K/(' * depth + 's+1' + ')' * depth, '1/(1+' * depth + 's' + ')' * depth,
                       'K' + '**2' * depth, '+' * depth + 'K/(s+1)'])


def _unicode(rng: random.Random) -> str:
    text = rng.choice(['K*exp(-tau*s)/(T*s + 1)', '1/(m*s**2 + d*s + k)', 'K/(s+1)'])
    position = rng.randint(0, len(text))
    return text[:position] + rng.choice(_UNICODE) + text[position:]


def _keyword(rng: random.Random) -> str:
    word = rng.choice(keyword.kwlist + ['print', 'exit', 'self', 'os', 'sys', 'exp', 'pi', 's'])
    return rng.choice([f'K/({word}*s + 1)', f'{word}/(s+1)', f'K*exp(-{word}*s)/(s+1)',
                       f'{word}(K)/(s+1)', f'K/(s+{word})'])


def _injection(rng: random.Random) -> str:
    return rng.choice(_INJECTIONS)


def _soup(rng: random.Random) -> str:
    return ''.join(rng.choice(_TOKENS) for _ in range(rng.randint(1, 40)))


def _grammar(rng: random.Random) -> str:
    return _expression(rng, rng.randint(1, 6))


def _long(rng: random.Random) -> str:
    count = rng.randint(100, 700)
    return rng.choice(['+'.join(['K'] * count) + '/(s+1)',
                       '+'.join(f'a{i}*b{i % 7}' for i in range(count // 3)) + '/(s+c)',
                       'K/(' + '+'.join(f'a{i % 60}*s**{i % 33}' for i in range(count // 4)) + ')',
                       'K/(s+1)*' + '*'.join(['(s+1)/(s+1)'] * (count // 12)),
                       'K*' + '*'.join(['1.5'] * count) + '/(s+1)',
                       ' ' * 1990 + 'K/(s+1)', 'K/(s+1)' + ' ' * 3000])


def _equation(rng: random.Random) -> str:
    return rng.choice([
        f'{_name(rng)}*s**2*y + {_name(rng)}*s*y = {_name(rng)}*u - off',
        f'{_expression(rng, 2, False)}*y = {_expression(rng, 2, False)}*u',
        'M*s**2*y + Fv*s*y = 35.15*u - Fc*w - off', 'y = u', 'y*y = u', 'y = u/y',
        'y = exp(-t*s)*u', 's*y = s*off + u', f'a*s*y + y = b*exp(-{_name(rng)}*s)*u',
        'y = u = 1', '= u', 'y =',
        f'({_expression(rng, 3, False)})*y + y = u'])


GENERATORS: List[Tuple[str, Callable[[random.Random], str]]] = [
    ('grammar', _grammar), ('plausible', _plausible), ('product', _product), ('lags', _lags),
    ('dense', _dense), ('black box', _black_box), ('nested power', _nested_power),
    ('exp', _exponentials), ('nesting', _nesting), ('unicode', _unicode),
    ('keyword', _keyword), ('injection', _injection), ('token soup', _soup), ('long', _long),
    ('equation', _equation),
]


def corpus(seed: int, count: int) -> List[Tuple[str, str]]:
    """
    Return ``count`` hostile texts as ``(generator name, text)``, the same for the same seed.

    Parameters
    ----------
    seed : int
        Seed of the generator.
    count : int
        Number of texts; the generators take turns so every kind is present.

    Returns
    -------
    list of (str, str)
        Generator name and text.

    """
    rng = random.Random(seed)
    texts = []
    for index in range(count):
        name, generator = GENERATORS[index % len(GENERATORS)]
        texts.append((name, generator(rng)))
    return texts
